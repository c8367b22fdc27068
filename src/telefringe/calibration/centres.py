"""Where a circle's image centre lies: the bias of detected circle centres.

A detector of circular markers (an ellipse fit, a centroid) finds the centre of a
circle's *image*, which is not the image of the circle's centre: perspective moves it
(the eccentricity of a pinhole camera) and so does the curvature of lens distortion, for
any model (a distorted circle's image is not an ellipse about the projected centre;
under radial distortion x (1 + k1 r^2) a disc's image centroid moves by 3 k1 rho^2 times
its distance from the axis, rho the circle's radius on the sensor: a magnification error,
2.6e-5 on the fast rig's camera). Both the calibration (which adjusts to detected
centres) and the measurement of a circle plate (which reads the cloud at detected
centres) correct for it with :func:`circle_image_centres`, through the device's full
model.

The image centre is the area centroid of the image of the disc, written as boundary
integrals (Green's theorem) over the projected circle, ``A = 1/2 int (x y' - y x') dt``,
``A c_x = 1/2 int x^2 y' dt``, ``A c_y = -1/2 int y^2 x' dt``, with the derivatives
``(x', y')`` from the device's point Jacobian. The integrands are smooth and periodic in
the circle's angle t, so the trapezoidal rule converges geometrically: 64 nodes are
exact to rounding for any device without a fold inside the marker
(tests/test_plate_centre_bias.py bounds it against 4096 nodes and against the ellipse
centre of an affine image). To first order in the departure of the image from an
ellipse, the area centroid is also the centre an ellipse fit finds (on rendered
markers within the detection noise: tests/test_centre_bias.py).
"""

from __future__ import annotations

import numpy as np

__all__ = ["circle_image_centres", "in_plane_basis"]

#: Nodes on each circle (see the module notes: exact to rounding on smooth images).
N_BOUNDARY = 64


def in_plane_basis(normals) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors (m, 3) each, orthogonal to each other and to ``normals`` (m, 3)
    (any orthonormal basis of the plane: a circle does not depend on which)."""
    n = np.asarray(normals, dtype=np.float64)
    n = n / np.linalg.norm(n, axis=-1, keepdims=True)
    helper = np.where((np.abs(n[..., 0]) < 0.9)[..., None], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0])
    e1 = np.cross(n, helper)
    e1 /= np.linalg.norm(e1, axis=-1, keepdims=True)
    return e1, np.cross(n, e1)


def circle_image_centres(device, centres, normals, radius, *,
                         n_boundary: int = N_BOUNDARY) -> np.ndarray:
    """Image centres of circles: the area centroids of their images through a device.

    Parameters
    ----------
    device : a Device (its ``project`` and ``project_jacobian``; any model).
    centres : (m, 3) array_like, mm, the circles' centres (world frame).
    normals : (m, 3) or (3,) array_like, the circles' plane normals (world, any length).
    radius : float or (m,) array_like, mm.
    n_boundary : int, nodes on each circle (the default is exact to rounding, see the
        module notes).

    Returns
    -------
    (m, 2) ndarray, px: where a detector finds each circle's centre. Subtract
    ``device.project(centres)`` for the bias of a detected centre.
    """
    C = np.asarray(centres, dtype=np.float64).reshape(-1, 3)
    m = C.shape[0]
    N = np.broadcast_to(np.asarray(normals, dtype=np.float64), (m, 3))
    r = np.broadcast_to(np.asarray(radius, dtype=np.float64), (m,))
    e1, e2 = in_plane_basis(N)
    th = 2.0 * np.pi * np.arange(int(n_boundary)) / int(n_boundary)
    cs, sn = np.cos(th), np.sin(th)
    X = (C[:, None, :] + r[:, None, None] * (cs[None, :, None] * e1[:, None, :]
                                             + sn[None, :, None] * e2[:, None, :]))
    dX = r[:, None, None] * (-sn[None, :, None] * e1[:, None, :]
                             + cs[None, :, None] * e2[:, None, :])
    uv, _, J = device.project_jacobian(X.reshape(-1, 3))
    uv = uv.reshape(m, -1, 2)
    duv = np.einsum("nij,nj->ni", J, dX.reshape(-1, 3)).reshape(m, -1, 2)
    # about the image of the centre: small numbers, no cancellation
    ref = np.stack(device.project(C), axis=1)
    x = uv[..., 0] - ref[:, 0, None]
    y = uv[..., 1] - ref[:, 1, None]
    xp, yp = duv[..., 0], duv[..., 1]
    area = 0.5 * np.mean(x * yp - y * xp, axis=1)
    cx = 0.5 * np.mean(x * x * yp, axis=1) / area
    cy = -0.5 * np.mean(y * y * xp, axis=1) / area
    return ref + np.stack([cx, cy], axis=1)
