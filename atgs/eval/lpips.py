"""LPIPS (Zhang et al. 2018, v0.1, AlexNet backbone), computed only from weights already on disk.

LPIPS needs two weight files that no package here ships together and that this machine cannot
download (no internet besides PyPI, and nothing is ever downloaded at run time):

* the ImageNet AlexNet backbone as torchvision saves it, ``alexnet-owt-7be5be79.pth``, looked
  up in the torch hub cache (``$TORCH_HOME/hub/checkpoints``, default ``~/.cache/torch/hub``);
* the LPIPS linear heads ``alex.pth`` (v0.1), looked up inside an installed ``lpips`` package
  (``lpips/weights/v0.1/alex.pth``; the package itself is never imported: it needs
  torchvision, whose PyPI wheel does not load beside our torch build).

Either file can be given explicitly. When one is missing, :func:`load_lpips` returns ``None``
and a one-line reason, and evaluation reports LPIPS as "unavailable" — never a made-up number.

The network is written here (layer shapes of torchvision's AlexNet ``features``); the weights
are read with ``torch.load(weights_only=True)`` so no pickled code runs.
"""

from __future__ import annotations

import importlib.util
from dataclasses import dataclass
from pathlib import Path

import torch
import torch.nn as nn
import torch.nn.functional as F

ALEXNET_FILE = "alexnet-owt-7be5be79.pth"
# torchvision AlexNet ``features`` indices of the five convolutions: (index, in, out, kernel, stride, pad)
_ALEX_CONVS = ((0, 3, 64, 11, 4, 2), (3, 64, 192, 5, 1, 2), (6, 192, 384, 3, 1, 1),
               (8, 384, 256, 3, 1, 1), (10, 256, 256, 3, 1, 1))
LPIPS_CHANNELS = tuple(c[2] for c in _ALEX_CONVS)
# LPIPS input normalisation of [-1, 1] images (the "ScalingLayer" constants of LPIPS v0.1)
_SHIFT = (-0.030, -0.088, -0.188)
_SCALE = (0.458, 0.448, 0.450)


@dataclass(frozen=True)
class LpipsWeights:
    backbone: Path | None
    linear: Path | None

    @property
    def available(self) -> bool:
        return self.backbone is not None and self.linear is not None


def default_backbone_path() -> Path:
    return Path(torch.hub.get_dir()) / "checkpoints" / ALEXNET_FILE


def default_linear_path() -> Path | None:
    """``alex.pth`` inside an installed ``lpips`` package, found without importing it."""
    try:
        spec = importlib.util.find_spec("lpips")
    except (ImportError, ValueError):
        return None
    if spec is None or not spec.submodule_search_locations:
        return None
    return Path(next(iter(spec.submodule_search_locations))) / "weights" / "v0.1" / "alex.pth"


def find_lpips_weights(backbone: Path | None = None, linear: Path | None = None) -> tuple[LpipsWeights, str]:
    """Locate both weight files; returns what was found and a reason when something is missing."""
    b = Path(backbone) if backbone is not None else default_backbone_path()
    lin = Path(linear) if linear is not None else default_linear_path()
    missing = []
    if not b.is_file():
        missing.append(f"AlexNet backbone weights not found at {b} (put torchvision's {ALEXNET_FILE} there "
                       "or pass --lpips-backbone)")
    if lin is None or not lin.is_file():
        where = lin if lin is not None else "an installed 'lpips' package"
        missing.append(f"LPIPS linear weights alex.pth not found in {where} (pass --lpips-linear)")
    found = LpipsWeights(b if b.is_file() else None, lin if lin is not None and lin.is_file() else None)
    return found, "; ".join(missing)


class LPIPS(nn.Module):
    """LPIPS distance with the AlexNet backbone; inputs (H,W,3) or (N,H,W,3) in [0,1] with both
    sides at least :attr:`MIN_SIZE` pixels (smaller images do not survive AlexNet's pooling)."""

    MIN_SIZE = 31

    def __init__(self) -> None:
        super().__init__()
        self.convs = nn.ModuleList(nn.Conv2d(i, o, k, stride=s, padding=p) for _, i, o, k, s, p in _ALEX_CONVS)
        self.lins = nn.ParameterList(nn.Parameter(torch.zeros(1, c, 1, 1)) for c in LPIPS_CHANNELS)
        self.register_buffer("shift", torch.tensor(_SHIFT).view(1, 3, 1, 1))
        self.register_buffer("scale", torch.tensor(_SCALE).view(1, 3, 1, 1))
        self.requires_grad_(False)
        self.eval()

    def load_weights(self, backbone: dict[str, torch.Tensor], linear: dict[str, torch.Tensor]) -> None:
        """``backbone``: torchvision AlexNet state dict (``features.<i>.weight/bias``);
        ``linear``: LPIPS v0.1 heads (``lin<k>.model.1.weight``, shape (1, C_k, 1, 1))."""
        for conv, (idx, *_rest) in zip(self.convs, _ALEX_CONVS):
            conv.weight.copy_(_get(backbone, f"features.{idx}.weight", conv.weight.shape))
            conv.bias.copy_(_get(backbone, f"features.{idx}.bias", conv.bias.shape))
        for k, lin in enumerate(self.lins):
            key = f"lin{k}.model.1.weight" if f"lin{k}.model.1.weight" in linear else f"lin{k}.weight"
            lin.copy_(_get(linear, key, lin.shape))

    def features(self, x: torch.Tensor) -> list[torch.Tensor]:
        """The five ReLU outputs LPIPS compares (relu1 .. relu5 of AlexNet)."""
        out = []
        for i, conv in enumerate(self.convs):
            if i in (1, 2):  # max-pool before conv2 and conv3
                x = F.max_pool2d(x, kernel_size=3, stride=2)
            x = F.relu(conv(x))
            out.append(x)
        return out

    @torch.no_grad()
    def forward(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        single = x.dim() == 3
        if min(x.shape[-3], x.shape[-2]) < self.MIN_SIZE:
            raise ValueError(f"LPIPS needs images of at least {self.MIN_SIZE}x{self.MIN_SIZE} px, got "
                             f"{x.shape[-2]}x{x.shape[-3]}")
        a = (x if not single else x.unsqueeze(0)).permute(0, 3, 1, 2).float()
        b = (y if not single else y.unsqueeze(0)).permute(0, 3, 1, 2).float()
        a = ((a * 2 - 1) - self.shift) / self.scale
        b = ((b * 2 - 1) - self.shift) / self.scale
        total = torch.zeros(a.shape[0])
        for fa, fb, w in zip(self.features(a), self.features(b), self.lins):
            na = fa / (fa.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)  # unit length per pixel
            nb = fb / (fb.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)
            total = total + ((na - nb) ** 2 * w).sum(1).mean((1, 2))
        return total[0] if single else total


def _get(sd: dict[str, torch.Tensor], key: str, shape: torch.Size) -> torch.Tensor:
    if key not in sd:
        raise ValueError(f"weight '{key}' missing")
    t = sd[key]
    if tuple(t.shape) != tuple(shape):
        raise ValueError(f"weight '{key}' has shape {tuple(t.shape)}, expected {tuple(shape)}")
    return t


def load_lpips(backbone: Path | None = None, linear: Path | None = None) -> tuple[LPIPS | None, str]:
    """The LPIPS network, or ``None`` and the reason it is unavailable (nothing is downloaded)."""
    found, reason = find_lpips_weights(backbone, linear)
    if not found.available:
        return None, reason
    net = LPIPS()
    try:
        b = torch.load(found.backbone, map_location="cpu", weights_only=True)
        lin = torch.load(found.linear, map_location="cpu", weights_only=True)
        net.load_weights(b, lin)
    except Exception as e:  # a corrupt or foreign file: report, do not crash the evaluation
        return None, f"LPIPS weights unusable ({found.backbone}, {found.linear}): {type(e).__name__}: {e}"
    return net, ""
