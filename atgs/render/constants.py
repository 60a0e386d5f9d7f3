"""Numerical constants shared by every rasterizer backend (SPEC section 2).

Backends must agree bit-for-bit on *which* Gaussian touches which pixel, so every threshold
lives here and the C++ kernel receives them as arguments instead of hard-coding its own.
"""

NEAR: float = 0.01  # default view-space z at or below which a Gaussian is culled (gsplat's near plane);
# a model renders with its own, scaled to its scene (ATGSModel.near, atgs.model.near_plane)
DILATION: float = 0.3  # px^2 added to the 2D covariance (EWA low-pass filter)
CLAMP_MARGIN: float = 0.3  # Jacobian clamp: x/z limited to (W - cx)/fx + 0.3 * tan(fov_x / 2)
RADIUS_SIGMAS: float = 3.0  # radii (and the contribution cut-off) at 3 standard deviations
SIGMA_CUTOFF: float = 0.5 * RADIUS_SIGMAS**2  # skip a pixel whose Mahalanobis term exceeds 4.5
ALPHA_MAX: float = 0.99
ALPHA_MIN: float = 1.0 / 255.0
T_MIN: float = 1e-4  # stop a pixel when T * (1 - alpha) would fall below this
QUAT_EPS: float = 1e-8  # quaternions are normalized as q / max(|q|, QUAT_EPS)
MAX_RADIUS: int = 1 << 24  # radii are clamped so that huge splats stay representable as int32
