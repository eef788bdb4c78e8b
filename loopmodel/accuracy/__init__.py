"""Accuracy of camera position from a marker contour: the Cramér–Rao bound of seed 001.

Conventions (units of the noise intensity, shared by the bound and the Monte-Carlo):

* Image-plane lengths are pixels of pitch ``pixel_um`` (default 10 um); the focal length in
  pixels is ``F = focal_mm * 1000 / pixel_um``. The marker has contrast 1 (brightness 1 on
  the marker, 0 on the background).
* ``noise`` is ``N0/2``, the two-sided spectral density of the white image noise in
  contrast^2 * px^2: the noise averaged over a 1 px x 1 px cell has variance ``N0/2``
  (so the paper's 0.2 means a per-pixel noise sigma of 0.447 for 10 um pixels). A cell of
  h x h px then has noise variance ``(N0/2) / h^2``.
* The contour formula ``J = (2/N0) * integral (n.Q_i)(n.Q_j) dl`` carries an implicit length:
  with a perfectly sharp edge and white noise, the information grows without bound as the
  sampling gets finer (it is proportional to 1/pixel size). The formula is exactly the
  Fisher information of the marker image seen through an isotropic Gaussian point-spread
  function of sigma ``PSF_SIGMA_PX = 1/(2 sqrt(pi)) = 0.282 px`` and sampled infinitely finely
  (``integral g(x)^2 dx = 1 px^-1`` for its line-spread function g), up to corner terms of
  relative size ~ sigma/edge length. It also equals, for edges along the pixel rows/columns,
  the information of a sharp image integrated over 1 px pixels (about 0.9-1.0 of it for
  other edge directions). The Monte-Carlo (``montecarlo``) renders exactly the first model, and
  ``pixels`` integrates it over pixels of finite size.
"""

from loopmodel.accuracy.fisher import (
    PHI_GRID_DEG,
    RHO_NAMES,
    THETA_GRID_DEG,
    Bound,
    GridBound,
    bound_grid,
    crlb,
    fisher_contour,
)
from loopmodel.accuracy.marker import (
    Circle,
    Marker,
    Polygon,
    load_marker,
    marker_from_dict,
    t_marker,
    triangle_marker,
)
from loopmodel.accuracy.view import PARAMS, Views, flows, focal_px, project, stabilised_views

#: Gaussian PSF sigma (px) for which the contour formula is the exact Fisher information.
PSF_SIGMA_PX = 0.28209479177387814  # 1 / (2 sqrt(pi))

__all__ = [
    "PARAMS",
    "PHI_GRID_DEG",
    "PSF_SIGMA_PX",
    "RHO_NAMES",
    "THETA_GRID_DEG",
    "Bound",
    "Circle",
    "GridBound",
    "Marker",
    "Polygon",
    "Views",
    "bound_grid",
    "crlb",
    "fisher_contour",
    "flows",
    "focal_px",
    "load_marker",
    "marker_from_dict",
    "project",
    "stabilised_views",
    "t_marker",
    "triangle_marker",
]
