"""One compiled solve shared by the pyramid levels (jaxcr.segmentation.refine, issue 18).

refine_frame pads every level's data to the finest level's grid, draws the merged tube with a
traced level (silhouette.level_tube_padded), masks the band slots past the level's band size
and gives the solver a traced step budget. These tests check each piece against the per-level
computation it replaces (the reference: the unpadded level, level_tube, a static
``max_steps``), and that a two-level refinement traces the solve once. No refinement program
is compiled here (tracing only), so the module costs seconds.
"""

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest

import jaxcr.segmentation.refine as refine_mod
from jaxcr.segmentation.energy import (
    Weights,
    chan_vese_energy,
    pyramid,
    region_data_from_level,
)
from jaxcr.segmentation.refine import ImageSpaceBFGS, _level_tables, refine_frame
from jaxcr.segmentation.silhouette import (
    TubeImage,
    level_tube,
    level_tube_padded,
    project_tube,
    select_band,
)
from tests.helpers import refine_scene
from tests.helpers.jitted import colour_mask  # compiled: input construction only
from tests.helpers.tube_render import render_tube

W, H, CFG = refine_scene.W, refine_scene.H, refine_scene.CFG


def _tube_with_gap(n=41):
    """A projected arc of n - 1 capsules, two of which (behind the camera) are invalid."""
    tube = project_tube(refine_scene.camera(), refine_scene.base())
    valid = np.ones(n - 1, bool)
    valid[[5, 17]] = False
    return TubeImage(tube.ax, tube.ay, tube.bx, tube.by, tube.ra, tube.rb, jnp.asarray(valid))


@pytest.mark.parametrize("level", [0, 1, 2])
@pytest.mark.parametrize("merge", [1, 2, 3])
def test_level_tube_padded_matches_level_tube(level, merge):
    """The traced-level drawing equals level_tube's on its capsules (same gathers and the
    same affine map, so equal up to float32 rounding of the scale factor: 1 ulp of ~100 px,
    1e-5 px with margin) and pads with invalid capsules."""
    tube = _tube_with_gap()
    ref = level_tube(tube, level, merge)
    size = -(-tube.ax.shape[0] // merge)  # the finest (level 0) count
    got = jax.jit(level_tube_padded, static_argnums=(2, 3))(tube, jnp.int32(level), merge, size)
    n = ref.ax.shape[0]
    for f in ("ax", "ay", "bx", "by", "ra", "rb"):
        np.testing.assert_allclose(getattr(got, f)[:n], getattr(ref, f), atol=1e-5, rtol=0)
    np.testing.assert_array_equal(got.valid[:n], ref.valid)
    assert not np.any(np.asarray(got.valid[n:]))


@eqx.filter_jit
def _level_inputs(base, cam, ip, bgm, level):
    """The inputs of _scene_level by one compiled program (op by op, the pyramid, the tables
    and the slicing were ~100 XLA compilations of single primitives)."""
    pyr = pyramid(ip, bgm, 2)
    tables = _level_tables([pyr], CFG, base.p.shape[0] - 1, jnp.float32)
    lv = jax.tree.map(lambda x: x[CFG.levels.index(level)], tables)
    ref_data = region_data_from_level(*pyr[level], level, CFG.tile)
    return project_tube(cam, base), lv, ref_data


def _scene_level(level):
    """Per-level data (the reference) and the padded, stacked tables of a two-level config."""
    base, cam = refine_scene.base(), refine_scene.camera()
    img, _ = render_tube(base, cam, 3, (W, H))
    bgm, ip = colour_mask(jnp.asarray(img))
    tube, lv, ref_data = _level_inputs(base, cam, ip, bgm, level)
    return tube, lv, lv.n_capsules, ref_data


@pytest.mark.parametrize("local", [False, True])
def test_padded_coarse_level_energy_matches_per_level(local):
    """Level 1 on the padded level-0 grid gives the per-level band, energy and gradient.

    Reference: select_band + chan_vese_energy on the unpadded level-1 data with
    level_tube, as refine_frame computed each level before. The band is the same tile set
    (mapped between the two grids); J is a float32 sum over the same pixels in another
    order plus zero-weight padding. Its rounding is a few eps times the magnitude of the
    largest cancelling term, the whole-image moment total_s2 (non-local) against J's data
    term normalised by the tube area (~1/50 of the image): 50 * 4e-7 relative ~ 2e-5, so
    rtol 2e-4 for J and 2e-3 for the gradient (one more summation, over band pixels).
    """
    tube, lv, size, ref_data = _scene_level(1)
    w = Weights(CFG.g_in, CFG.g_out, CFG.g_reg, CFG.g_pen)
    area = jnp.asarray(400.0)
    k1 = min(CFG.tiles_at(1), ref_data.grid.n_tiles)
    # the tube 1.5 px off the rendered one: a sizeable gradient
    fields = (tube.ax + 1.5, tube.ay, tube.bx + 1.5, tube.by, tube.ra, tube.rb)

    def ref(fs):
        t = level_tube(TubeImage(*fs, tube.valid), 1, CFG.seg_merge)
        band = select_band(t, ref_data.grid, k1, CFG.k_seg)
        return chan_vese_energy(t, band, ref_data, 0.0, w, 1.0, area, local)[0], band

    def padded(fs):
        data = lv.datas[0]
        t = level_tube_padded(TubeImage(*fs, tube.valid), lv.level, CFG.seg_merge, size)
        band = select_band(t, data.grid, lv.k_max[0], CFG.k_seg, lv.tile_ok[0], lv.k_active[0])
        return chan_vese_energy(t, band, data, 0.0, w, lv.tau, area, local)[0], band

    (j_ref, band_ref), g_ref = jax.jit(jax.value_and_grad(ref, has_aux=True))(fields)
    (j_pad, band_pad), g_pad = jax.jit(jax.value_and_grad(padded, has_aux=True))(fields)
    # the same band tiles: (row, col) of the active slots on the padded grid
    cols_ref, cols_pad = ref_data.grid.cols, lv.datas[0].grid.cols
    t_ref = np.asarray(band_ref.tiles)
    t_pad = np.asarray(band_pad.tiles)[np.asarray(band_pad.active)]
    assert sorted(zip(t_ref // cols_ref, t_ref % cols_ref, strict=True)) == sorted(
        zip(t_pad // cols_pad, t_pad % cols_pad, strict=True)
    )
    assert np.isclose(float(lv.tau), CFG.tau[0])
    np.testing.assert_allclose(j_pad, j_ref, rtol=2e-4)
    for a, b in zip(g_pad, g_ref, strict=True):
        scale = float(jnp.max(jnp.abs(b)))
        np.testing.assert_allclose(a, b, atol=2e-3 * scale, rtol=0)


def _quadratic(y, args):
    return jnp.sum(args * (y - 1.0) ** 2) + 0.5 * (y[0] - y[1]) ** 2


@pytest.mark.parametrize("budget", [1, 3, 40])
def test_step_budget_matches_static_max_steps(budget):
    """A traced step budget ends a solve exactly as Optimistix's static max_steps does: the
    same iterate, step count and status (the same steps are taken, so equal to rounding)."""
    a = jnp.asarray([1.0, 30.0, 0.3])
    y0 = jnp.zeros(3)
    jac = jnp.eye(3)[None, :2]  # the "image motion" of a step: its first two coordinates
    opts = {"motion_jac": jnp.concatenate([jac, jnp.eye(3)[None, 1:]], axis=0)}
    solver = ImageSpaceBFGS(1e-6, 1e-12)

    def run(b, static):
        o = dict(opts, step_budget=b)
        return optx.minimise(
            _quadratic, solver, y0, args=a, options=o, max_steps=static, throw=False
        )

    ref = jax.jit(lambda: optx.minimise(_quadratic, solver, y0, args=a, options=opts,
                                        max_steps=budget, throw=False))()  # fmt: skip
    got = jax.jit(lambda b: run(b, 64))(jnp.int32(budget))
    assert int(got.stats["num_steps"]) == int(ref.stats["num_steps"])
    assert int(got.result._value) == int(ref.result._value)
    np.testing.assert_allclose(got.value, ref.value, rtol=1e-6, atol=1e-6)
    if budget == 1:
        assert int(got.result._value) == int(optx.RESULTS.nonlinear_max_steps_reached._value)


@pytest.mark.parametrize("share", [True, False])
def test_two_level_refine_traces_the_solve_once(monkeypatch, share):
    """The pyramid levels share one solve: tracing a two-level refine_frame calls
    optx.minimise once; with ``share_levels=False``, once per level (the per-level program)."""
    calls = []
    real = optx.minimise

    def counting(*args, **kwargs):
        calls.append(1)
        return real(*args, **kwargs)

    monkeypatch.setattr(refine_mod.optx, "minimise", counting)
    base, cam = refine_scene.base(), refine_scene.camera()
    img = jnp.zeros((H, W, 3))
    bg = jnp.zeros((H, W), bool)
    cfg = dataclasses.replace(CFG, share_levels=share)
    assert len(cfg.levels) == 2
    jax.make_jaxpr(lambda b, i, g: refine_frame(b, cam, i, g, cfg))(base, img, bg)
    assert len(calls) == (1 if share else 2)


def test_padded_level_gradient_is_nan_free_on_a_straight_tube():
    """Singular points of the new drawing: a straight tube (collinear capsules) with a
    zero-length capsule and a capsule merged across an invalid one, drawn at a traced coarse
    level on the padded grid; the energy's gradient with respect to the centreline's
    projection is finite."""
    _, lv, size, _ = _scene_level(1)
    n = 40
    x = jnp.linspace(20.0, 140.0, n + 1)
    x = x.at[10].set(x[9])  # capsule 9 has zero length
    y = jnp.full(n + 1, 60.0)
    valid = jnp.ones(n, bool).at[20].set(False)
    w = Weights(CFG.g_in, CFG.g_out, CFG.g_reg, CFG.g_pen)

    def energy(xy):
        px, py = xy
        t = TubeImage(px[:-1], py[:-1], px[1:], py[1:], jnp.full(n, 3.0), jnp.full(n, 3.0), valid)
        t = level_tube_padded(t, lv.level, CFG.seg_merge, size)
        data = lv.datas[0]
        band = select_band(t, data.grid, lv.k_max[0], CFG.k_seg, lv.tile_ok[0], lv.k_active[0])
        return chan_vese_energy(t, band, data, 0.0, w, lv.tau, jnp.asarray(500.0))[0]

    g = jax.jit(jax.grad(energy))((x, y))
    assert all(bool(jnp.all(jnp.isfinite(a))) for a in g)
    assert any(bool(jnp.any(a != 0)) for a in g)


def test_warm_schedule():
    """RefineConfig.warm(): the finest level, its budget, solves and tau, and a J-change
    tolerance WARM_FTOL_FACTOR times ftol (docs/decisions.md S18); a one-level config is its
    own warm schedule (refine_sequence then runs one program). Config arithmetic: exact."""
    warm = CFG.warm()
    assert (warm.levels, warm.steps, warm.outer, warm.tau) == ((0,), (15,), (1,), (0.8,))
    assert warm.ftol == refine_mod.WARM_FTOL_FACTOR * CFG.ftol and warm.xtol == CFG.xtol
    assert warm.warm() is warm
