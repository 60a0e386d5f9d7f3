"""Per-camera exposure: a gain and a bias per colour channel for each training camera.

Real rigs do not expose their cameras alike (on the N3DV frame five of the twenty training
cameras are ~20 % brighter than the others). The model's colours do not depend on the view, so
without this it can only bend its geometry towards each camera's brightness, and a held-out
camera gets whatever blend of those compromises its rays meet: a colour cast that changes with
the seed (docs/training.md, "Camera exposure").

Training renders camera ``i`` as ``image * exp(g_i) + b_i``. The gauge is fixed by the mean:
the values used are ``g_i - mean(g)`` and ``b_i - mean(b)``, so the model's own colours are the
training cameras' average exposure, which is what held-out cameras and the viewer render (no
correction). A uniform shift of every camera's parameters changes nothing.
"""

from __future__ import annotations

import torch


class CameraExposure:
    def __init__(self, num_cameras: int, lr: float, device: torch.device | str = "cpu") -> None:
        # (N, 6): log-gains of R, G, B, then biases; zeros are the identity
        self.table = torch.zeros(num_cameras, 6, device=device, requires_grad=True)
        self.opt = torch.optim.Adam([self.table], lr=lr, eps=1e-15)

    def gauge_fixed(self) -> torch.Tensor:
        """(N, 6) the parameters as used: every column minus its mean over the cameras."""
        return self.table - self.table.mean(0, keepdim=True)

    def gains_biases(self) -> tuple[torch.Tensor, torch.Tensor]:
        """(N, 3) gains and (N, 3) biases, detached (for reports and checkpoints)."""
        p = self.gauge_fixed().detach()
        return p[:, :3].exp(), p[:, 3:]

    def apply(self, image: torch.Tensor, slot: int) -> torch.Tensor:
        """``image`` (H, W, 3) as training camera ``slot`` (its index among the training cameras) saw it."""
        p = self.gauge_fixed()[slot]
        return image * p[:3].exp() + p[3:]

    def step(self, clip: float) -> None:
        g = self.table.grad
        if g is None:
            return
        torch.nan_to_num_(g, nan=0.0, posinf=0.0, neginf=0.0)
        if clip > 0:
            torch.nn.utils.clip_grad_norm_([self.table], clip)
        self.opt.step()
        self.opt.zero_grad(set_to_none=True)

    def state_dict(self) -> dict:
        return {"table": self.table.detach().clone(), "opt": self.opt.state_dict()}

    def load_state_dict(self, state: dict) -> None:
        table = state["table"].to(self.table.device)
        if table.shape != self.table.shape:
            raise ValueError(f"exposure table of {table.shape[0]} cameras, this run trains {self.table.shape[0]}")
        with torch.no_grad():
            self.table.copy_(table)
        self.opt.load_state_dict(state["opt"])
