"""Projected tube silhouette: 2-D capsules, hard rasterisation and a band-limited soft mask.

The tube surface of Watson et al. eq. 7 (a circle of radius rho(s) swept along the
centreline) projects (eqs. 3-4) to nearly the union of 2-D capsules: for each centreline
segment, the projected end points and the apparent radius ``r_img = f * rho / depth``. A pixel
centre ``y`` is inside capsule i when its *margin*

    m_i(y) = r_i(t) - |y - (a_i + t (b_i - a_i))|,   t = clip(<y - a_i, b_i - a_i> / |b_i - a_i|^2, 0, 1),
    r_i(t) = (1 - t) ra_i + t rb_i,

is positive; the silhouette margin is ``m(y) = max_i m_i(y)`` (a signed distance in pixels,
positive inside). The hard rasterisation is ``m > 0`` and the soft silhouette is
``sigmoid(m / tau)``, whose 0.5-level is exactly the hard rasterisation.

Speed: the gradient of a region energy only lives near the silhouette boundary, so the image
is cut into square tiles and only a fixed number ``k_tiles`` of tiles nearest the boundary (a
*band*, chosen under ``stop_gradient`` from the current shape) is evaluated per pixel; each
band tile also keeps the ``k_seg`` segments with the largest margin at its centre, so each
band pixel evaluates only those candidates. Tiles outside the band are classified whole by
the margin at their centre (exact when the band reaches farther than half a tile diagonal,
see :attr:`Band.exact`). All sizes are static, so one compile serves a whole dataset.

Pixel convention (as :mod:`jaxcr.camera`): the centre of pixel (row i, column j) is at
``(x, y) = (j, i)``. Pyramid level ``l`` pixels are ``2**l`` full-resolution pixels wide, with
``x_l = (x + 0.5) / 2**l - 0.5``.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from jaxcr._types import Array, Bool, Float, Int
from jaxcr.camera import Camera, project_xy
from jaxcr.kinematics.cosserat import Centreline

OFF_IMAGE_MARGIN = -1e4  # margin (px) given to segments behind the camera


class TubeImage(eqx.Module):
    """A projected tube as 2-D capsules, one per centreline segment (pixels).

    Attributes:
        ax, ay, bx, by: (m,) segment end points (pixel coordinates, x = column, y = row).
        ra, rb: (m,) apparent radius at each end (pixels).
        valid: (m,) segment lies in front of the camera.
    """

    ax: Float[Array, " m"]
    ay: Float[Array, " m"]
    bx: Float[Array, " m"]
    by: Float[Array, " m"]
    ra: Float[Array, " m"]
    rb: Float[Array, " m"]
    valid: Bool[Array, " m"]


def project_tube(
    camera: Camera, centreline: Centreline, near: float = 1e-4, size=None
) -> TubeImage:
    """Project a centreline's tube (Watson et al. eq. 7 drawn by eqs. 3-4) to 2-D capsules.

    End points are projected with the full camera model (distortion included); the apparent
    radius is ``sqrt(fx fy) * rho / Z`` with ``Z`` the camera-frame depth (distortion of the
    radius itself is neglected). Segments with an end behind ``near`` are invalid.

    ``size``: (height, width), possibly traced, of the real image when ``camera``'s own size
    is a larger padded one (shape buckets, :mod:`jaxcr.segmentation.buckets`): the end points
    are then clamped to that image's box as a camera of that size clamps them
    (:func:`jaxcr.camera.project_xy`; a clamp inside the camera's own, larger box).
    """
    u, v, _ = project_xy(camera, centreline.p, near)
    if size is not None:
        h, w = (jnp.asarray(x, u.dtype) for x in size)
        u = jnp.clip(u, -w, 2.0 * w)
        v = jnp.clip(v, -h, 2.0 * h)
    z = centreline.p @ camera.R[2] + camera.t[2]
    in_front = z > near
    f = jnp.sqrt(camera.K[0, 0] * camera.K[1, 1])
    r = f * centreline.rho / jnp.where(in_front, z, 1.0)
    r = jnp.where(in_front, r, 0.0)
    valid = in_front[1:] & in_front[:-1]
    return TubeImage(u[:-1], v[:-1], u[1:], v[1:], r[:-1], r[1:], valid)


def scale_tube(tube: TubeImage, level: int) -> TubeImage:
    """The same capsules in the pixel grid of pyramid level ``level`` (2**level downsampling)."""
    if level == 0:
        return tube
    k = 1.0 / (2**level)

    def c(x):
        return (x + 0.5) * k - 0.5

    return TubeImage(
        c(tube.ax), c(tube.ay), c(tube.bx), c(tube.by), tube.ra * k, tube.rb * k, tube.valid
    )


def coarsen_tube(tube: TubeImage, stride: int) -> TubeImage:
    """Merge runs of ``stride`` consecutive capsules into one (from the first one's start to
    the last one's end; invalid if any member is). The last run may be shorter.

    Band tiles evaluate a fixed number of candidate segments (``k_seg``), which must span the
    tile along the tube. At pyramid level ``l`` the segments of a centreline shrink to
    ``2**-l`` of their full-resolution length while tiles keep their size in level pixels, so
    :func:`level_tube` merges ``2**l`` segments: a segment then covers about as many level
    pixels at every level. The chord error this adds is ``L**2 / (8 R)`` for merged length
    ``L`` and bend radius ``R`` (micrometres for centimetre-scale bends), far below a pixel.
    """
    if stride <= 1:
        return tube
    m = tube.ax.shape[0]
    starts = jnp.arange(0, m, stride)
    ends = jnp.minimum(starts + stride - 1, m - 1)
    n = starts.shape[0]
    pad = n * stride - m
    valid = jnp.concatenate([tube.valid, jnp.ones(pad, bool)]).reshape(n, stride).all(axis=1)
    return TubeImage(
        tube.ax[starts],
        tube.ay[starts],
        tube.bx[ends],
        tube.by[ends],
        tube.ra[starts],
        tube.rb[ends],
        valid,
    )


def level_tube(tube: TubeImage, level: int, merge: int = 1) -> TubeImage:
    """The tube drawn at pyramid level ``level``: :func:`scale_tube` to the level's pixel grid,
    then :func:`coarsen_tube` by ``merge * 2**level`` so segments keep their length in level
    pixels (``merge`` times the full-resolution segment length)."""
    return coarsen_tube(scale_tube(tube, level), merge * 2**level)


def level_tube_padded(tube: TubeImage, level: Int[Array, ""], merge: int, size: int) -> TubeImage:
    """:func:`level_tube` for a *traced* pyramid level, padded to ``size`` capsules.

    One compiled program can then draw the tube at every level of a pyramid (the
    refinement's solves share one level body, :func:`jaxcr.segmentation.refine.refine_frame`):
    capsule ``i`` merges segments ``i s .. i s + s - 1`` (``s = merge * 2**level``, the last
    run may be shorter, as :func:`coarsen_tube`), and capsules past the tube's end are
    invalid (their margin is ``OFF_IMAGE_MARGIN``: they never win a pixel nor a band slot).
    ``size`` must be at least the number of capsules at the finest level drawn,
    ``ceil(m / (merge * 2**level_min))``. Equal to :func:`level_tube` on the valid capsules.
    """
    m = tube.ax.shape[0]
    level = jnp.asarray(level, jnp.int32)
    k = jnp.exp2(-level.astype(tube.ax.dtype))

    def c(x):
        return (x + 0.5) * k - 0.5

    stride = merge * jnp.left_shift(jnp.asarray(1, jnp.int32), level)
    starts = jnp.arange(size, dtype=jnp.int32) * stride
    live = starts < m
    starts = jnp.minimum(starts, m - 1)
    ends = jnp.minimum(starts + stride - 1, m - 1)
    # invalid members of a run by differences of a running count
    bad = jnp.concatenate([jnp.zeros(1, jnp.int32), jnp.cumsum((~tube.valid).astype(jnp.int32))])
    valid = live & (bad[ends + 1] - bad[starts] == 0)
    return TubeImage(
        c(tube.ax[starts]),
        c(tube.ay[starts]),
        c(tube.bx[ends]),
        c(tube.by[ends]),
        tube.ra[starts] * k,
        tube.rb[ends] * k,
        valid,
    )


def capsule_margin(px, py, ax, ay, bx, by, ra, rb, valid):
    """Margin (px) of points ``(px, py)`` w.r.t. capsules, elementwise with broadcasting.

    Positive inside. Differentiable everywhere (double-where at zero distance and for
    degenerate segments of zero length).
    """
    dx, dy = bx - ax, by - ay
    wx, wy = px - ax, py - ay
    l2 = dx * dx + dy * dy
    ok = l2 > 1e-12
    t = jnp.clip((wx * dx + wy * dy) / jnp.where(ok, l2, 1.0), 0.0, 1.0)
    t = jnp.where(ok, t, 0.0)
    ex, ey = wx - t * dx, wy - t * dy
    d2 = ex * ex + ey * ey
    pos = d2 > 1e-12
    d = jnp.where(pos, jnp.sqrt(jnp.where(pos, d2, 1.0)), 0.0)
    m = ra + t * (rb - ra) - d
    return jnp.where(valid, m, OFF_IMAGE_MARGIN)


def margin_dense(
    px: Float[Array, " p"], py: Float[Array, " p"], tube: TubeImage
) -> tuple[Float[Array, " p"], Int[Array, " p"]]:
    """Silhouette margin max_i m_i at points (p,) against all segments, and the best segment.

    Memory is (p, m): use for small point sets (tile centres, tests).
    """
    m = capsule_margin(
        px[:, None],
        py[:, None],
        tube.ax[None],
        tube.ay[None],
        tube.bx[None],
        tube.by[None],
        tube.ra[None],
        tube.rb[None],
        tube.valid[None],
    )
    return jnp.max(m, axis=1), jnp.argmax(m, axis=1)


def rasterise_dense(tube: TubeImage, height: int, width: int) -> Bool[Array, "h w"]:
    """Exact hard silhouette (margin > 0 at every pixel centre), row by row. Reference
    implementation: slower than :func:`rasterise` but independent of tiles and bands."""
    xs = jnp.arange(width, dtype=tube.ax.dtype)

    def row(y):
        m, _ = margin_dense(xs, jnp.full_like(xs, y), tube)
        return m > 0

    return jax.lax.map(row, jnp.arange(height, dtype=tube.ax.dtype))


# ----------------------------------------------------------------------------------------
# Tiles and bands


class TileGrid(eqx.Module):
    """Static tiling of an ``height x width`` image into ``tile x tile`` squares (padded)."""

    height: int = eqx.field(static=True)
    width: int = eqx.field(static=True)
    tile: int = eqx.field(static=True)

    @property
    def rows(self) -> int:
        return -(-self.height // self.tile)

    @property
    def cols(self) -> int:
        return -(-self.width // self.tile)

    @property
    def n_tiles(self) -> int:
        return self.rows * self.cols

    @property
    def n_pix(self) -> int:
        return self.tile * self.tile

    def to_tiles(self, image: Array, fill=0) -> Array:
        """(h, w, ...) -> (n_tiles, tile*tile, ...), padding with ``fill``."""
        t = self.tile
        ph, pw = self.rows * t - self.height, self.cols * t - self.width
        pad = [(0, ph), (0, pw)] + [(0, 0)] * (image.ndim - 2)
        x = jnp.pad(image, pad, constant_values=fill)
        x = x.reshape((self.rows, t, self.cols, t) + image.shape[2:])
        x = jnp.swapaxes(x, 1, 2)
        return x.reshape((self.n_tiles, t * t) + image.shape[2:])

    def from_tiles(self, tiles: Array) -> Array:
        """(n_tiles, tile*tile, ...) -> (h, w, ...), cropping the padding."""
        t = self.tile
        x = tiles.reshape((self.rows, self.cols, t, t) + tiles.shape[2:])
        x = jnp.swapaxes(x, 1, 2)
        x = x.reshape((self.rows * t, self.cols * t) + tiles.shape[2:])
        return x[: self.height, : self.width]

    def row_col(self, tiles: Int[Array, "..."]) -> tuple[Int[Array, "..."], Int[Array, "..."]]:
        """Row and column of tile indices ``tiles`` (>= 0): truncating integer division, the
        same values as ``//`` and ``%`` on non-negative indices without their sign fix-ups
        (fewer operations in every compiled copy of the band energy)."""
        cols = jnp.asarray(self.cols, tiles.dtype)
        return jax.lax.div(tiles, cols), jax.lax.rem(tiles, cols)

    def tile_centres(self, dtype=jnp.float32) -> tuple[Array, Array]:
        """(n_tiles,) x and y of each tile's centre (pixel coordinates)."""
        t = self.tile
        cy = jnp.arange(self.rows, dtype=dtype) * t + (t - 1) / 2.0
        cx = jnp.arange(self.cols, dtype=dtype) * t + (t - 1) / 2.0
        return jnp.tile(cx, self.rows), jnp.repeat(cy, self.cols)

    def pixel_offsets(self, dtype=jnp.float32) -> tuple[Array, Array]:
        """(tile*tile,) x and y offsets of a tile's pixels from its top-left pixel."""
        t = self.tile
        o = jnp.arange(t, dtype=dtype)
        return jnp.tile(o, t), jnp.repeat(o, t)


class Band(eqx.Module):
    """Tiles near a silhouette boundary, chosen without gradient (see module docstring).

    Attributes:
        tiles: (k_tiles,) indices of the band tiles (into the tile grid).
        segs: (k_tiles, k_seg) candidate segment indices per band tile.
        inside: (n_tiles,) tile outside the band and classified inside the silhouette.
        exact: scalar bool, every tile outside the band lies wholly on one side (its centre
            margin exceeds half the tile diagonal) and every band tile's candidates include
            every segment that can be the nearest one at one of its pixels, so the band mask
            equals the exact one.
        active: (k_tiles,) bool or None: which slots belong to the band (None: all). A band
            of a traced size ``k_active`` (:func:`select_band`) keeps ``k_tiles`` slots; the
            slots past ``k_active`` are inactive, and the region sums give their pixels
            zero weight (:func:`jaxcr.segmentation.energy.region_terms`).
    """

    tiles: Int[Array, " k"]
    segs: Int[Array, "k c"]
    inside: Bool[Array, " n"]
    exact: Bool[Array, ""]
    active: Bool[Array, " k"] | None = None


def select_band(
    tube: TubeImage,
    grid: TileGrid,
    k_tiles: int,
    k_seg: int,
    tile_ok: Bool[Array, " n"] | None = None,
    k_active: Int[Array, ""] | None = None,
) -> Band:
    """Choose the ``k_tiles`` tiles whose centres are nearest the silhouette boundary.

    Runs under ``stop_gradient``. ``k_tiles`` and ``k_seg`` are clipped to the grid and
    segment counts.

    ``tile_ok`` (n_tiles,) and ``k_active`` (a traced count <= ``k_tiles``) serve an image
    padded to a larger grid (a coarse pyramid level drawn on the finest level's grid): tiles
    with ``tile_ok`` False never enter the band, and only the ``k_active`` nearest tiles
    are band tiles (:attr:`Band.active`); the others are classified whole by their centre,
    like every tile outside the band. The band is then the one :func:`select_band` picks on
    the unpadded grid with ``k_tiles = k_active`` (up to the order of tiles of equal
    distance).
    """
    tube = jax.lax.stop_gradient(tube)
    k_tiles = min(k_tiles, grid.n_tiles)
    n_seg = tube.ax.shape[0]
    k_seg = min(k_seg, n_seg)
    cx, cy = grid.tile_centres(tube.ax.dtype)
    m = capsule_margin(
        cx[:, None],
        cy[:, None],
        tube.ax[None],
        tube.ay[None],
        tube.bx[None],
        tube.by[None],
        tube.ra[None],
        tube.rb[None],
        tube.valid[None],
    )  # (n_tiles, n_seg)
    mc = jnp.max(m, axis=1)
    key = -jnp.abs(mc) if tile_ok is None else jnp.where(tile_ok, -jnp.abs(mc), -jnp.inf)
    # the barriers keep XLA:CPU's TopK: without them it folds the slices taken below into
    # the top_k and runs a full sort of every row instead (the output band's 384 x 96
    # candidates: ~1.9 ms a call at 640x480; profile_fixed_ops_640_*.md, decisions S24)
    neg_abs, tiles = jax.lax.optimization_barrier(jax.lax.top_k(key, k_tiles))
    half_diag = grid.tile * 0.7072
    if k_seg < n_seg:
        # a segment can win at some pixel of the tile only if its centre margin is within
        # 2 * half_diag of the best (margins are 1-Lipschitz); the candidates are complete
        # when the best left-out segment is below that
        top, segs = jax.lax.optimization_barrier(jax.lax.top_k(m[tiles], k_seg + 1))
        segs = segs[:, :k_seg]
        complete = jnp.all(top[:, k_seg] < top[:, 0] - 2.0 * half_diag)
    else:
        _, segs = jax.lax.top_k(m[tiles], k_seg)
        complete = jnp.asarray(True)
    if k_active is None:
        in_band = jnp.zeros(grid.n_tiles, bool).at[tiles].set(True)
        inside = (mc > 0) & ~in_band
        exact = ((k_tiles == grid.n_tiles) | (-neg_abs[-1] >= half_diag)) & complete
        return Band(tiles=tiles, segs=segs, inside=inside, exact=exact)
    active = jnp.arange(k_tiles) < k_active
    in_band = jnp.zeros(grid.n_tiles, bool).at[tiles].set(active)
    inside = (mc > 0) & ~in_band
    n_ok = grid.n_tiles if tile_ok is None else jnp.sum(tile_ok)
    last = -neg_abs[jnp.clip(k_active - 1, 0, k_tiles - 1)]
    exact = ((k_active >= n_ok) | (last >= half_diag)) & complete
    return Band(tiles=tiles, segs=segs, inside=inside, exact=exact, active=active)


def band_margin(tube: TubeImage, grid: TileGrid, band: Band) -> Float[Array, "k p"]:
    """Margin (px) of every pixel of every band tile, differentiable w.r.t. ``tube``.

    Each pixel takes the max over its tile's candidate segments. The max's gradient flows to
    the winning segment only, so the winner is found without gradient and only its margin is
    differentiated: the same value and gradient as differentiating ``max`` over all
    candidates (up to float rounding and the split of ties), at about a third of the cost of
    that gradient on CPU with 4 candidates.
    """
    dtype = tube.ax.dtype
    t = grid.tile
    ox, oy = grid.pixel_offsets(dtype)
    row, col = grid.row_col(band.tiles)
    tx = col.astype(dtype) * t
    ty = row.astype(dtype) * t
    px = tx[:, None] + ox[None]  # (k, p)
    py = ty[:, None] + oy[None]
    fields = (tube.ax, tube.ay, tube.bx, tube.by, tube.ra, tube.rb)
    valid = _take(tube.valid, band.segs)[:, None, :]  # (k, 1, c)
    cand = [_take(jax.lax.stop_gradient(a), band.segs)[:, None, :] for a in fields]
    m_all = capsule_margin(px[..., None], py[..., None], *cand, valid)  # (k, p, c)
    best = jnp.argmax(m_all, axis=-1)
    seg = jnp.take_along_axis(band.segs, best, axis=1, mode="promise_in_bounds")  # (k, p)
    return capsule_margin(px, py, *(_take(a, seg) for a in fields), _take(tube.valid, seg))


def _take(a: Array, idx: Int[Array, "..."]) -> Array:
    """``a[idx]`` for indices known to be in bounds and non-negative (segment indices from
    ``top_k``/``argmax``): the same gather without the wrapping of negative indices and the
    out-of-bounds fill, which every compiled copy of the band energy would otherwise carry."""
    return a.at[idx].get(mode="promise_in_bounds", wrap_negative_indices=False)


def rasterise(
    tube: TubeImage, height: int, width: int, tile: int = 8, k_tiles: int = 1024, k_seg: int = 16
) -> tuple[Bool[Array, "h w"], Bool[Array, ""]]:
    """Hard silhouette (margin > 0 at pixel centres) via a band of tiles: fast, and exact when
    the returned flag is True (the band reached every tile the boundary crosses)."""
    grid = TileGrid(height, width, tile)
    band = select_band(tube, grid, k_tiles, k_seg)
    m = band_margin(tube, grid, band)
    tiles = jnp.broadcast_to(band.inside[:, None], (grid.n_tiles, grid.n_pix))
    tiles = tiles.at[band.tiles].set(m > 0)
    return grid.from_tiles(tiles), band.exact
