"""Independent tube renderer shared by the refinement tests (not jaxcr's rasteriser).

Watson eq. 7 surface points are projected with the camera, the convex hull of each pair of
consecutive rings (OpenCV) is filled at pixel centres (scikit-image), and the tube is drawn
grey over a noisy red background.
"""

import cv2
import equinox as eqx
import numpy as np
from skimage.draw import polygon

from jaxcr.camera import project_points, surface_points


@eqx.filter_jit
def _surface_uv(cl, cam):
    """Pixel positions (N, 16, 2) of the Watson eq. 7 surface rings: one compiled program per
    shape (op by op, every primitive of the rings and the projection was an XLA compilation of
    its own, in every module that renders)."""
    pts = surface_points(cl, 16)
    uv, _ = project_points(cam, pts.reshape(-1, 3))
    return uv.reshape(pts.shape[0], 16, 2)


def render_tube(cl, cam, seed: int, size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Image (h, w, 3) float32 in [0, 1] and tube mask (h, w) bool for centreline ``cl``."""
    W, H = size
    uv = np.asarray(_surface_uv(cl, cam))
    mask = np.zeros((H, W), bool)
    for i in range(uv.shape[0] - 1):
        hull = cv2.convexHull(np.concatenate([uv[i], uv[i + 1]]).astype(np.float32))[:, 0]
        rr, cc = polygon(hull[:, 1], hull[:, 0], mask.shape)
        mask[rr, cc] = True
    rng = np.random.default_rng(seed)
    img = np.empty((H, W, 3), np.float32)
    img[:] = [0.70, 0.25, 0.25]
    img += rng.normal(0, 0.05, img.shape).astype(np.float32)
    img[mask] = [0.6, 0.6, 0.62]
    img[mask] += rng.normal(0, 0.03, (mask.sum(), 3)).astype(np.float32)
    return np.clip(img, 0, 1), mask


def arc_base(radius: float, n: int = 41):
    """Nominal test centreline: a 12 cm planar arc (curvature 6 /m) leaving (-0.06, 0.01, 0)
    along +x, body x towards -z (towards the camera of :func:`front_camera`)."""
    import jax.numpy as jnp

    from tests.helpers.jitted import integrate_centreline  # compiled: input construction only

    s = jnp.linspace(0.0, 0.12, n)
    u = jnp.tile(jnp.array([6.0, 0.0, 0.0]), (n - 1, 1))
    R0 = jnp.array([[0.0, 0, 1], [0, 1, 0], [-1, 0, 0]])
    return integrate_centreline(s, u, jnp.full(n, radius), jnp.array([-0.06, 0.01, 0.0]), R0)


def front_camera(fx: float, size: tuple[int, int]):
    """Camera 0.3 m in front of the arc's plane, looking at the origin."""
    from jaxcr.camera import Camera

    return Camera.look_at([0, 0, -0.3], [0, 0, 0], [0, -1, 0], fx=fx, size=size)


def tube_frames(base, cam, coeffs, size: tuple[int, int]) -> list[dict]:
    """One rendered, colour-masked frame per delta-u coefficient array: dicts with the
    background-subtracted image ``img``, background ``bg``, truth ``mask`` and centreline
    ``truth``."""
    import jax.numpy as jnp

    from tests.helpers.jitted import colour_mask, perturbed_centreline  # input construction

    frames = []
    for k, c in enumerate(coeffs):
        truth_cl = perturbed_centreline(base, jnp.asarray(c))
        img, mask = render_tube(truth_cl, cam, k, size)
        bg, ip = colour_mask(jnp.asarray(img))
        frames.append(dict(img=ip, bg=bg, mask=mask, truth=truth_cl))
    return frames
