"""Tube diameter along the backbone from the silhouette widths in both views.

Width in one view (sub-pixel): the foreground alpha (anti-aliased, from
:mod:`jaxcr.stereo.chroma`) is sampled along the image normal of the backbone through each
backbone point; the contiguous run of foreground around the centre is integrated, giving
the width ``w = sum(alpha) * step`` and the centre offset (first moment). Edge pixels carry
fractional alpha, so the width is not quantised to whole pixels.

Diameter from a width ("cylinder" method, ours): the two silhouette edges seen by a camera
with centre ``C`` lie on the two planes through ``C`` tangent to the tube; both contain the
line through ``C`` parallel to the tube axis ``t``. Projected along ``t``, the edge rays
``e1``, ``e2`` enclose the angle ``2 alpha`` and ``r = D_perp sin(alpha)`` with ``D_perp``
the distance of ``C`` from the axis line. Exact for a cylinder, for any orientation of the
axis, as long as the axis is not parallel to the viewing ray (then the silhouette is a disc;
such views get a small weight ``sin`` of the angle between ``t`` and the ray).

The report's "3-D interpolation" (sec. 5.1.1): metres per pixel from the 3-D step between
consecutive backbone points over its pixel length, times the pixel width,
``d_s = |dP_perp| / p * d_p`` per view, averaged over the two views. Here ``dP_perp`` is the
step's component perpendicular to the optical axis (the report assumed perfectly
perpendicular views and dropped the depth coordinate; this is the same assumption written
for any camera). It over-estimates where the tube points towards a camera (report Fig. 10).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from jaxcr._types import Array, Float
from jaxcr.camera import Camera, pixel_rays

__all__ = [
    "profile_widths",
    "cylinder_diameters",
    "report_interpolation_diameters",
    "view_weights",
    "edge_clearance",
]


def _sample(img, uv):
    coords = jnp.stack([uv[..., 1].ravel(), uv[..., 0].ravel()])
    out = jax.scipy.ndimage.map_coordinates(img, coords, order=1, mode="nearest")
    return out.reshape(uv.shape[:-1])


def profile_widths(
    alpha: Float[Array, "h w"],
    centres_uv: Float[Array, "n 2"],
    normals_uv: Float[Array, "n 2"],
    key_proj: Float[Array, "h w"] | None = None,
    half_length: float = 16.0,
    step: float = 0.25,
    cut: float = 0.5,
) -> tuple[Float[Array, " n"], Float[Array, " n"]]:
    """Widths (n,) in pixels across the silhouette and the offset (n,) of the silhouette's
    centre along the unit ``normals_uv`` from ``centres_uv`` (pixels).

    The run of foreground (``alpha >= cut``) through the sample nearest the centre gives
    the silhouette's extent (other parts of the robot nearby are not added). Its edges are
    then located to sub-pixel precision. With ``key_proj`` (the key-colour projection
    ``(rgb - mean(rgb)) . k_hat``, which is *linear* in the mixing of tube and cloth inside
    an edge pixel) each edge's coverage is unmixed linearly between the local cloth level
    (mean of the samples 2-4 px outside the edge) and the tube level just inside it;
    without it, ``alpha`` is integrated over the run and one sample beyond."""
    offs = jnp.arange(-half_length, half_length + step / 2, step)
    uv = centres_uv[:, None, :] + offs[None, :, None] * normals_uv[:, None, :]
    a = _sample(alpha, uv)
    c = offs.shape[0] // 2
    on = a >= cut
    right = jnp.cumprod(on[:, c:], axis=1)
    left = jnp.cumprod(on[:, : c + 1][:, ::-1], axis=1)[:, ::-1]
    run = jnp.concatenate([left[:, :-1], right], axis=1).astype(a.dtype)
    n_left = jnp.sum(left, axis=1) - 1  # run samples left of the centre
    n_right = jnp.sum(right, axis=1) - 1
    lo = offs[c] - n_left * step  # first/last run sample offsets (pixels)
    hi = offs[c] + n_right * step
    if key_proj is None:
        edge = jnp.maximum(
            jnp.pad(run[:, 1:], ((0, 0), (0, 1))), jnp.pad(run[:, :-1], ((0, 0), (1, 0)))
        )
        wgt = a * edge
        width = jnp.sum(wgt, axis=1) * step
        offset = jnp.sum(wgt * offs[None], axis=1) / jnp.maximum(jnp.sum(wgt, axis=1), 1e-9)
        return width, offset
    g = _sample(key_proj, uv)
    o = offs[None, :]

    def side(edge_pos, sign):
        # sign = -1: left edge at edge_pos (run starts there); +1: right edge.
        outside = sign * (o - edge_pos)  # > 0 outside the run
        bg_sel = (outside >= 2.0) & (outside <= 4.0)
        fg_sel = (outside <= -1.25) & (outside >= -1.75)
        # Means over the few samples of each window (a median costs a sort per profile).
        bg = jnp.sum(jnp.where(bg_sel, g, 0.0), axis=1) / jnp.maximum(jnp.sum(bg_sel, axis=1), 1)
        nf = jnp.sum(fg_sel, axis=1)
        fg = jnp.sum(jnp.where(fg_sel, g, 0.0), axis=1) / jnp.maximum(nf, 1)
        fg = jnp.where(nf > 0, fg, jnp.min(jnp.where(run > 0, g, jnp.inf), axis=1))
        # Grid samples at outside = -1.25, -1.0, ..., 1.75 (the edge sample is on the grid)
        # each stand for a cell of one step: together [-1.25 - step/2, 2 - step/2).
        zone = (outside > -1.25 - 1e-3) & (outside < 2.0 - 1e-3)
        den = bg - fg
        cover = jnp.clip(
            (bg[:, None] - g) / jnp.where(jnp.abs(den) > 1e-6, den, 1e-6)[:, None], 0, 1
        )
        # Coverage integrated over the transition zone, measured from 1.25 px inside.
        return jnp.sum(jnp.where(zone, cover, 0.0), axis=1) * step

    cl = side(lo[:, None], -1.0)
    cr = side(hi[:, None], 1.0)
    inner = 1.25 + step / 2
    left_edge = lo - (cl - inner)
    right_edge = hi + (cr - inner)
    width = jnp.maximum(right_edge - left_edge, 0.0)
    offset = 0.5 * (left_edge + right_edge)
    return width, offset


def cylinder_diameters(
    camera: Camera,
    axis_points: Float[Array, "n 3"],
    axis_dirs: Float[Array, "n 3"],
    centres_uv: Float[Array, "n 2"],
    normals_uv: Float[Array, "n 2"],
    widths: Float[Array, " n"],
    offsets: Float[Array, " n"],
) -> Float[Array, " n"]:
    """Diameters (n,) in metres from silhouette widths of one view (see module docstring).

    ``axis_points``/``axis_dirs`` in the camera's world frame (the base frame); the edges
    are at ``centre + (offset -+ width/2) * normal`` in pixels."""
    lo = centres_uv + (offsets - widths / 2)[:, None] * normals_uv
    hi = centres_uv + (offsets + widths / 2)[:, None] * normals_uv
    C, e1 = pixel_rays(camera, lo)
    _, e2 = pixel_rays(camera, hi)
    t = axis_dirs / jnp.linalg.norm(axis_dirs, axis=1, keepdims=True)

    def perp(e):
        p = e - jnp.sum(e * t, axis=1, keepdims=True) * t
        return p / jnp.sqrt(jnp.sum(p * p, axis=1, keepdims=True) + 1e-30)

    p1, p2 = perp(e1), perp(e2)
    cos2a = jnp.clip(jnp.sum(p1 * p2, axis=1), -1.0, 1.0)
    half = 0.5 * jnp.arccos(cos2a)
    rel = axis_points - C
    rel_perp = rel - jnp.sum(rel * t, axis=1, keepdims=True) * t
    d_perp = jnp.sqrt(jnp.sum(rel_perp**2, axis=1))
    return 2.0 * d_perp * jnp.sin(half)


def view_weights(camera: Camera, axis_points: Float[Array, "n 3"], axis_dirs: Float[Array, "n 3"]):
    """sin of the angle between the tube axis and the viewing ray (1 = seen side-on)."""
    ray = axis_points - camera.centre
    ray = ray / jnp.linalg.norm(ray, axis=1, keepdims=True)
    t = axis_dirs / jnp.linalg.norm(axis_dirs, axis=1, keepdims=True)
    c = jnp.sum(ray * t, axis=1)
    return jnp.sqrt(jnp.clip(1.0 - c * c, 0.0, 1.0))


def report_interpolation_diameters(
    camera: Camera,
    points: Float[Array, "n 3"],
    uv: Float[Array, "n 2"],
    widths: Float[Array, " n"],
) -> Float[Array, " n"]:
    """The report's 3-D interpolation (sec. 5.1.1) for one view: per point i, metres per
    pixel ``|(P[i+1] - P[i]) perp optical axis| / |uv[i+1] - uv[i]|`` times the pixel width
    (the last point reuses the previous step). Average the two views' results."""
    dP = jnp.diff(points, axis=0)
    z = camera.R[2]
    dP_perp = dP - (dP @ z)[:, None] * z
    p = jnp.linalg.norm(jnp.diff(uv, axis=0), axis=1)
    scale = jnp.linalg.norm(dP_perp, axis=1) / jnp.maximum(p, 1e-9)
    scale = jnp.concatenate([scale, scale[-1:]])
    return scale * widths


def edge_clearance(
    alpha: Float[Array, "h w"],
    centres_uv: Float[Array, "n 2"],
    normals_uv: Float[Array, "n 2"],
    widths: Float[Array, " n"],
    offsets: Float[Array, " n"],
    gap: tuple[float, float] = (2.0, 4.0),
    cut: float = 0.5,
) -> Float[Array, " n"]:
    """True (as 1.0) where both silhouette edges measured by :func:`profile_widths` have
    clean background beside them: ``alpha < cut`` at every sample ``gap`` pixels (default
    2-4, the window :func:`profile_widths` takes the cloth level from) outside each edge.

    Where another part of the robot lies beside the tube in the image (a curled tip next
    to the shaft), the cloth level is taken from the wrong material and the edge, hence
    the width and the centre, are wrong; callers drop that view's measurement there. Pass
    ``alpha`` restricted to the robot (other foreground, e.g. markers, is then ignored)."""
    g = jnp.linspace(gap[0], gap[1], 5)
    lo = offsets - widths / 2
    hi = offsets + widths / 2
    offs = jnp.concatenate([lo[:, None] - g[None], hi[:, None] + g[None]], axis=1)
    uv = centres_uv[:, None, :] + offs[..., None] * normals_uv[:, None, :]
    a = _sample(alpha, uv)
    return jnp.all(a < cut, axis=1).astype(alpha.dtype)
