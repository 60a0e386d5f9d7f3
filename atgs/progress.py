"""One place that styles the tqdm progress bars of long ATGS jobs."""

from __future__ import annotations

from tqdm import tqdm


def progress_bar(total: int, desc: str, *, unit: str = "it", enabled: bool = True, initial: int = 0) -> tqdm:
    """A tqdm bar with the project's defaults (width follows the terminal, at most 2 updates/s);
    ``initial``: work already done (a resumed run)."""
    return tqdm(total=total, desc=desc, unit=unit, disable=not enabled, dynamic_ncols=True,
                mininterval=0.5, smoothing=0.1, initial=initial)
