"""Region energy of Watson et al. eq. 5 with the Chan-Vese data terms of eq. 6.

    E = g1 * int_{R - B} |I' - mu_in|^2 + g2 * int_{R^c - B} |I' - mu_out|^2
        + g3 * E_reg(delta-u) + g4 * |R intersect B|

with R the projected tube, B the background pixels (:mod:`jaxcr.segmentation.background`), I' the
background-subtracted RGB image and mu_in/out the mean colours of R - B and R^c - B (eq. 6).
Each data integral only needs three moments of its region: with ``S0 = sum w``, ``S1 = sum w
I``, ``S2 = sum w |I|^2`` (``w`` = 1 on pixels outside B), ``int |I - mu|^2 = S2 - |S1|^2 / S0``.
The moments of R^c are the image totals minus those of R, and R is small, so only the
moments of R are accumulated: over the band pixels with the soft silhouette (see
:mod:`jaxcr.segmentation.silhouette`) and over whole tiles inside R from per-tile sums. The image is
centred on its mean data colour first, so the float32 sums stay accurate.

Units: pixels are counted in full-resolution pixels at every pyramid level (a level-l pixel
counts ``4**l``), colours are RGB in [0, 1]. The solver minimises the dimensionless

    J = [g1 E_in + g2 (E_out - E_out(R = empty))] / (A_ref var) + g3 E_reg + g4 E_pen / A_ref,

where ``A_ref`` is the nominal silhouette area and ``var`` the mean squared centred colour,
so that the terms are of the same order of magnitude whatever the image and tube size (as
Watson et al. advise for their weights).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from jaxcr._types import Array, Bool, Float, Int
from jaxcr.segmentation.silhouette import Band, TileGrid, TubeImage, band_margin


class RegionData(eqx.Module):
    """One image at one pyramid level, padded to whole tiles, ready for region sums.

    Attributes:
        grid: the tiling (static).
        w: (H, W) data weight of each pixel: fraction of the pixel outside B (0 on padding).
        b: (H, W) background weight: fraction of the pixel in B (0 on padding).
        img: (H, W, 3) centred colour ``I' - centre`` (0 where w = 0).
        tile_w, tile_b, tile_s2: (n_tiles,) per-tile sums of w, b and w |img|^2.
        tile_s1: (n_tiles, 3) per-tile sums of w img.
        total_w, total_s2: scalars, image totals of w and w |img|^2; total_s1: (3,).
        centre: (3,) the colour subtracted (weighted mean colour of the data pixels).
        pix_area: full-resolution pixels per pixel at this level (``4**level``); a float, or
            a scalar array when one compiled program serves several levels.

    ``H, W`` are the image size rounded up to whole tiles.
    """

    grid: TileGrid
    w: Float[Array, "H W"]
    b: Float[Array, "H W"]
    img: Float[Array, "H W 3"]
    tile_w: Float[Array, " n"]
    tile_b: Float[Array, " n"]
    tile_s1: Float[Array, "n 3"]
    tile_s2: Float[Array, " n"]
    total_w: Float[Array, ""]
    total_s1: Float[Array, " 3"]
    total_s2: Float[Array, ""]
    centre: Float[Array, " 3"]
    pix_area: float | Float[Array, ""]

    def gather(self, tiles: Int[Array, " k"]) -> tuple[Array, Array, Array]:
        """Pixels of the given tiles: w (k, p), b (k, p), img (k, p, 3), p = tile**2, in
        row-major order within each tile (as :meth:`TileGrid.pixel_offsets`)."""
        t = self.grid.tile
        row, col = self.grid.row_col(tiles)
        r0, c0 = row * t, col * t

        # each array sliced on its own: a stack of the three (one gather) is a copy of the
        # whole image per frame, ~8 ms at 1280x720 (profile_fixed_ops_step_1280_s28.md, S28)
        def of(x):
            def one(r, c):
                start = (r, c) + (jnp.zeros_like(r),) * (x.ndim - 2)
                return jax.lax.dynamic_slice(x, start, (t, t) + x.shape[2:])

            return jax.vmap(one)(r0, c0).reshape((tiles.shape[0], t * t) + x.shape[2:])

        return of(self.w), of(self.b), of(self.img)


def downsample(
    image: Float[Array, "h w 3"], w: Float[Array, "h w"], b: Float[Array, "h w"]
) -> tuple[Float[Array, "h2 w2 3"], Float[Array, "h2 w2"], Float[Array, "h2 w2"]]:
    """One pyramid step: 2x2 averages of the weights and the data-weighted mean colour.

    Odd sizes are padded at the bottom/right with zero weight (pixel j of the new level
    covers pixels 2j, 2j+1 of the old one).
    """
    h, wd = w.shape
    ph, pw = h % 2, wd % 2
    image = jnp.pad(image, ((0, ph), (0, pw), (0, 0)))
    w = jnp.pad(w, ((0, ph), (0, pw)))
    b = jnp.pad(b, ((0, ph), (0, pw)))
    H, W = (h + ph) // 2, (wd + pw) // 2

    def pool(x):
        return x.reshape((H, 2, W, 2) + x.shape[2:]).sum(axis=(1, 3))

    sw = pool(w)
    si = pool(image * w[..., None])
    img = si / jnp.where(sw > 0, sw, 1.0)[..., None]
    return img, sw / 4.0, pool(b) / 4.0


def pyramid(
    image: Float[Array, "h w 3"],
    background: Bool[Array, "h w"],
    levels: int,
    valid: Bool[Array, "h w"] | None = None,
) -> list[tuple[Array, Array, Array]]:
    """Levels 0..levels-1 of ``(image, w, b)`` with w = not B and b = B as weights.

    ``valid``: the real pixels of an image padded to a larger shape (shape buckets,
    :mod:`jaxcr.segmentation.buckets`); the others get w = b = 0 (no data, no background), as
    the pixels :func:`downsample` adds for odd sizes, so every level's real part equals the
    unpadded image's."""
    b = background.astype(image.dtype)
    w = 1.0 - b
    if valid is not None:
        v = valid.astype(image.dtype)
        w, b = w * v, b * v
    out = [(image, w, b)]
    for _ in range(1, levels):
        out.append(downsample(*out[-1]))
    return out


def padded_level(img, w, b, tile: int):
    """One pyramid level ``(img, w, b)`` zero-padded to whole ``tile`` x ``tile`` tiles, and the
    image I' centred on its ``w``-weighted mean (0 where ``w`` is 0): ``(grid, img, w, b,
    total_w, centre)``, the inputs of :func:`region_data_from_level`'s per-tile sums."""
    h, wd = w.shape
    grid = TileGrid(h, wd, tile)
    H, W = grid.rows * tile, grid.cols * tile
    w = jnp.pad(w, ((0, H - h), (0, W - wd)))
    b = jnp.pad(b, ((0, H - h), (0, W - wd)))
    img = jnp.pad(img, ((0, H - h), (0, W - wd), (0, 0)))
    wi = w[..., None] * img
    total_w = jnp.sum(w)
    centre = jnp.sum(wi, axis=(0, 1)) / jnp.maximum(total_w, 1e-6)
    img = jnp.where(w[..., None] > 0, img - centre, 0.0)
    return grid, img, w, b, total_w, centre


def region_data_from_level(
    img: Float[Array, "h w 3"],
    w: Float[Array, "h w"],
    b: Float[Array, "h w"],
    level: int,
    tile: int,
) -> RegionData:
    """:class:`RegionData` from one pyramid level ``(img, w, b)`` (see :func:`pyramid`)."""
    grid, img, w, b, total_w, centre = padded_level(img, w, b, tile)

    def tsum(x):
        return x.reshape((grid.rows, tile, grid.cols, tile) + x.shape[2:]).sum(axis=(1, 3))

    tile_s1 = tsum(w[..., None] * img).reshape(grid.n_tiles, 3)
    tile_s2 = tsum(w * jnp.sum(img * img, axis=-1)).reshape(grid.n_tiles)
    return RegionData(
        grid=grid,
        w=w,
        b=b,
        img=img,
        tile_w=tsum(w).reshape(grid.n_tiles),
        tile_b=tsum(b).reshape(grid.n_tiles),
        tile_s1=tile_s1,
        tile_s2=tile_s2,
        total_w=total_w,
        total_s1=jnp.sum(tile_s1, axis=0),
        total_s2=jnp.sum(tile_s2),
        centre=centre,
        pix_area=float(4**level),
    )


def prepare_region_data(
    image: Float[Array, "h w 3"],
    background: Bool[Array, "h w"],
    level: int = 0,
    tile: int = 8,
) -> RegionData:
    """Build :class:`RegionData` for pyramid level ``level`` of a full-resolution image.

    Args:
        image: background-subtracted RGB image I' (float, [0, 1]).
        background: B, True on background pixels (excluded from the data terms).
        level: pyramid level (0 = full resolution).
        tile: tile size in pixels (static).
    """
    img, w, b = pyramid(image, background, level + 1)[level]
    return region_data_from_level(img, w, b, level, tile)


class RegionTerms(eqx.Module):
    """Eq. 5 terms in full-resolution pixels (colour terms in pixels x colour^2).

    Attributes:
        e_in: int_{R - B} |I' - mu_in|^2.
        e_out: int_{R^c - B} |I' - mu_out|^2.
        e_pen: |R intersect B| (pixels).
        area_in: |R - B| (pixels).
        area_out: |R^c - B| (pixels; within the band when ``local``).
        e_out_empty: e_out for an empty R (the constant the solver subtracts).
    """

    e_in: Float[Array, ""]
    e_out: Float[Array, ""]
    e_pen: Float[Array, ""]
    area_in: Float[Array, ""]
    area_out: Float[Array, ""]
    e_out_empty: Float[Array, ""]


def region_terms(
    soft: Float[Array, "k p"],
    band: Band,
    data: RegionData,
    local: bool = False,
    robust: float = 0.0,
    envelope: bool = False,
    gathered: tuple[Array, Array, Array] | None = None,
) -> RegionTerms:
    """Chan-Vese region terms (eq. 6) for a soft silhouette on the band and hard tiles inside.

    ``soft`` holds the silhouette value in [0, 1] of each band pixel (``band.tiles`` order).
    With ``local``, the outside region R^c is restricted to the band (the pixels near the
    silhouette), as in localised region-based active contours (Lankton & Tannenbaum 2008):
    mu_out is then the mean colour *around* the robot, not over the whole image.

    With ``robust = k > 0`` (a Python number > 0, or any array: the scale may be traced, the
    choice of term is not) the inside term is occlusion-robust: each band pixel contributes
    ``c^2 (1 - exp(-|I - mu_in|^2 / c^2))`` (Welsch) instead of ``|I - mu_in|^2``, with
    ``c^2 = k^2 * var`` and ``var`` the image's mean squared (centred) data colour, and
    mu_in the matching reweighted mean (two reweightings from the plain mean; the gradient
    flows through them, so it is exact for this definition). A pixel unlike the robot inside R (an occluder in front of it)
    then costs at most ``c^2`` rather than pushing the silhouette off it. Whole tiles inside
    R keep the quadratic term (they only occur for tubes several tiles wide).

    With ``envelope`` the robust term's gradient does not flow through the reweightings
    (mu_in is held constant, ``stop_gradient``): the value is unchanged and the gradient is
    the envelope-theorem gradient ``d/d soft_i = w_i rho(I_i - mu_in)`` of
    ``min_mu sum w rho(I - mu)``, exact when the reweightings have converged (then the
    derivative with respect to mu vanishes) and an approximation after two of them. It
    skips the backward pass through the reweightings (measured on the bench_segment scene:
    ms per solver step +17-24 % over the quadratic term instead of +60-75 %).

    ``gathered``: ``data.gather(band.tiles)`` computed once by the caller (a solver evaluates
    the energy many times on one band; the gather does not depend on the tube).
    """
    ins = band.inside.astype(soft.dtype)
    bw, bb, img = data.gather(band.tiles) if gathered is None else gathered
    if band.active is not None:
        # slots past a band of traced size: no pixel of theirs counts
        act = band.active.astype(bw.dtype)[:, None]
        bw, bb = bw * act, bb * act
    w = bw * soft
    s0 = jnp.sum(w) + jnp.dot(ins, data.tile_w)
    s1 = jnp.einsum("kp,kpc->c", w, img) + ins @ data.tile_s1
    s2 = jnp.sum(w * jnp.sum(img * img, axis=-1)) + jnp.dot(ins, data.tile_s2)
    pen = jnp.sum(bb * soft) + jnp.dot(ins, data.tile_b)
    eps = 1e-6
    e_in = s2 - jnp.sum(s1 * s1) / jnp.maximum(s0, eps)
    # an array scale (e.g. traced by the compiled refinement, docs/decisions.md S34) selects
    # the Welsch term; a Python number selects it when > 0
    if isinstance(robust, jax.Array) or robust > 0.0:
        c2 = robust**2 * data.total_s2 / jnp.maximum(data.total_w, eps)
        c2 = jax.lax.stop_gradient(jnp.maximum(c2, 1e-8))
        t_w, t_s1, t_s2 = jnp.dot(ins, data.tile_w), ins @ data.tile_s1, jnp.dot(ins, data.tile_s2)
        mu = s1 / jnp.maximum(s0, eps)
        for _ in range(2):
            r2 = jnp.sum((img - mu) ** 2, axis=-1)
            wr = w * jnp.exp(-r2 / c2)
            mu = (jnp.einsum("kp,kpc->c", wr, img) + t_s1) / jnp.maximum(jnp.sum(wr) + t_w, eps)
        if envelope:
            mu = jax.lax.stop_gradient(mu)
        r2 = jnp.sum((img - mu) ** 2, axis=-1)
        e_band = jnp.sum(w * c2 * (1.0 - jnp.exp(-r2 / c2)))
        e_tiles = t_s2 - 2.0 * jnp.dot(mu, t_s1) + jnp.sum(mu * mu) * t_w
        e_in = e_band + e_tiles
    if local:
        wo = bw * (1.0 - soft)
        s0o = jnp.sum(wo)
        s1o = jnp.einsum("kp,kpc->c", wo, img)
        s2o = jnp.sum(wo * jnp.sum(img * img, axis=-1))
        e_out = s2o - jnp.sum(s1o * s1o) / jnp.maximum(s0o, eps)
        e_out_empty = jnp.zeros_like(e_out)
    else:
        s0o = data.total_w - s0
        s1o = data.total_s1 - s1
        e_out = (data.total_s2 - s2) - jnp.sum(s1o * s1o) / jnp.maximum(s0o, eps)
        e_out_empty = data.total_s2 - jnp.sum(data.total_s1**2) / jnp.maximum(data.total_w, eps)
    a = data.pix_area
    return RegionTerms(
        e_in=a * jnp.maximum(e_in, 0.0),
        e_out=a * jnp.maximum(e_out, 0.0),
        e_pen=a * pen,
        area_in=a * s0,
        area_out=a * (jnp.sum(bw * (1.0 - soft)) if local else data.total_w - s0),
        e_out_empty=a * e_out_empty,
    )


def soft_band(tube: TubeImage, band: Band, grid: TileGrid, tau: float) -> Float[Array, "k p"]:
    """Soft silhouette sigmoid(margin / tau) on the band pixels (tau in level pixels)."""
    return jax.nn.sigmoid(band_margin(tube, grid, band) / tau)


class Weights(eqx.Module):
    """Weights gamma_1..4 of Watson et al. eq. 5 (on the normalised terms, see module doc)."""

    g_in: float = 1.0
    g_out: float = 1.0
    g_reg: float = 0.1
    g_pen: float = 1.0


def chan_vese_energy(
    tube: TubeImage,
    band: Band,
    data: RegionData,
    reg: Float[Array, ""],
    weights: Weights,
    tau: float,
    area_ref: Float[Array, ""],
    local: bool = False,
    robust: float = 0.0,
    var: Float[Array, ""] | None = None,
    envelope: bool = False,
    gathered: tuple[Array, Array, Array] | None = None,
) -> tuple[Float[Array, ""], dict[str, Float[Array, ""]]]:
    """Watson et al. eq. 5 (with eq. 6) for one image at one pyramid level.

    Args:
        tube: the projected tube at this level's pixel grid (:func:`silhouette.scale_tube`).
        band: band tiles for this tube (from :func:`silhouette.select_band`, no gradient).
        data: the image's :class:`RegionData` at this level.
        reg: E_reg, the dimensionless L * int |delta-u|^2 ds (:func:`shape.regularisation`).
        weights: gamma_1..4.
        tau: soft-silhouette temperature in this level's pixels.
        area_ref: reference silhouette area (full-resolution pixels) normalising the terms.
        local: restrict R^c to the band (see :func:`region_terms`).
        robust: occlusion-robust inside term (see :func:`region_terms`); 0 = eq. 6 as is.
        var: colour variance (colour^2) that normalises the data terms; None = the image's
            mean squared centred colour (module docstring). :func:`residual_variance` gives
            the regions' own noise variance instead (Gaussian likelihood of eq. 6).
        envelope: envelope-theorem gradient of the robust term (see :func:`region_terms`).
        gathered: the band's pixels, ``data.gather(band.tiles)``, if already gathered.

    Returns:
        ``(J, terms)``: the normalised objective minimised by the solver, and a dict with the
        raw terms ``e_in, e_out, e_reg, e_pen`` (eq. 5, full-resolution pixel units) and
        ``area_in``.
    """
    soft = soft_band(tube, band, data.grid, tau)
    J_image, t = chan_vese_soft(
        soft, band, data, weights, area_ref, local, robust, var, envelope, gathered
    )
    J = J_image + weights.g_reg * reg
    terms = {
        "e_in": t.e_in,
        "e_out": t.e_out,
        "e_reg": reg,
        "e_pen": t.e_pen,
        "area_in": t.area_in,
        "area_out": t.area_out,
    }
    return J, terms


def chan_vese_soft(
    soft: Float[Array, "k p"],
    band: Band,
    data: RegionData,
    weights: Weights,
    area_ref: Float[Array, ""],
    local: bool = False,
    robust: float = 0.0,
    var: Float[Array, ""] | None = None,
    envelope: bool = False,
    gathered: tuple[Array, Array, Array] | None = None,
) -> tuple[Float[Array, ""], RegionTerms]:
    """The image part of J (data and penalty terms, no regulariser) of :func:`chan_vese_energy`
    as a function of the soft silhouette ``soft`` on the band pixels (arguments as there).

    Returns ``(J_image, terms)``. Its gradient with respect to ``soft`` is the per-pixel
    weight of the Gauss-Newton form (:mod:`jaxcr.segmentation.least_squares`).
    """
    t = region_terms(soft, band, data, local, robust, envelope, gathered)
    if var is None:
        var = data.pix_area * data.total_s2 / jnp.maximum(data.pix_area * data.total_w, 1e-6)
    scale = jnp.maximum(area_ref, 1.0)
    data_term = (weights.g_in * t.e_in + weights.g_out * (t.e_out - t.e_out_empty)) / (
        scale * jnp.maximum(var, 1e-8)
    )
    return data_term + weights.g_pen * t.e_pen / scale, t


def residual_variance(terms: dict[str, Float[Array, ""]]) -> Float[Array, ""]:
    """Per-pixel noise variance of the piecewise-constant model of eq. 6 (colour^2):
    ``(e_in + e_out) / (|R - B| + |R^c - B|)`` from :func:`chan_vese_energy`'s terms, under
    ``stop_gradient``.

    Eq. 6 is the negative log-likelihood of Gaussian colour noise around mu_in and mu_out up
    to the factor ``1 / (2 sigma^2)``; normalising the data terms by this estimate of
    ``sigma^2`` (instead of the whole image's colour variance) weighs the data against the
    shape prior by how well the two-region model explains the pixels, not by how much the
    scene's colours vary overall (an image with a tissue-coloured background and a grey plate
    has a large colour variance but a small robot-to-surroundings contrast).
    """
    n = terms["area_in"] + terms["area_out"]
    v = (terms["e_in"] + terms["e_out"]) / jnp.maximum(n, 1e-6)
    return jax.lax.stop_gradient(jnp.maximum(v, 1e-8))
