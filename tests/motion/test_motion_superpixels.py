"""Superpixels, label propagation and LK flow of M-L (the speed-critical low-level stages)
against independent references: slow loops, numpy indexing, scikit-image and OpenCV called
directly. Small shapes, one compile per shape."""

from __future__ import annotations

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxcr.motion import flow as fm
from jaxcr.motion import superpixels as sp
from jaxcr.motion.propagate import (
    dominant_motion,
    labels_at_points,
    motion_priority,
    splat_labels,
    warp_labels,
)
from tests.helpers.slic_reference import slic_step_loop


@pytest.fixture(scope="module")
def step_fn():
    return jax.jit(sp.slic_step, static_argnums=(2, 3))


@pytest.fixture(scope="module")
def step_fn_reach():
    return jax.jit(sp.slic_step, static_argnums=(2, 3, 5))


def test_slic_step_vs_loop_with_tracked_labels(step_fn):
    """A label map that is not a grid (ids shuffled, one segment empty), as after tracking."""
    rng = np.random.default_rng(0)
    h, w, step, k = 20, 28, 6, 20
    lab = rng.normal(50, 12, (h, w, 3)).astype(np.float32)
    base = np.asarray(sp.grid_labels(h, w, step))  # 4 x 5 cells
    perm = rng.permutation(k)
    labels = perm[base]
    labels[labels == perm[7]] = perm[8]  # segment perm[7] is now empty
    labels = labels.astype(np.int32)
    ours = np.asarray(step_fn(jnp.asarray(lab), jnp.asarray(labels), k, step, 10.0))
    ref = slic_step_loop(lab.astype(np.float64), labels, k, step, 10.0)
    assert np.mean(ours == ref) > 0.995  # float32 near-ties may flip a pixel
    assert not np.any(ours == perm[7])
    eager = np.asarray(sp.slic_step(jnp.asarray(lab), jnp.asarray(labels), k, step, 10.0))
    np.testing.assert_array_equal(eager, ours)


@pytest.mark.parametrize("reach", [1, 3])
def test_slic_step_with_reach_vs_loop(step_fn_reach, reach):
    """The tracking refinement: candidates ``reach`` px apart instead of the grid step, on a
    tracked (shuffled, not grid) label map; and no pixel takes a label that was not among the
    nine labels ``reach`` px around it."""
    rng = np.random.default_rng(10 + reach)
    h, w, step, k = 20, 28, 6, 20
    lab = rng.normal(50, 12, (h, w, 3)).astype(np.float32)
    labels = rng.permutation(k)[np.asarray(sp.grid_labels(h, w, step))].astype(np.int32)
    ours = np.asarray(step_fn_reach(jnp.asarray(lab), jnp.asarray(labels), k, step, 10.0, reach))
    ref = slic_step_loop(lab.astype(np.float64), labels, k, step, 10.0, reach=reach)
    assert np.mean(ours == ref) > 0.995  # float32 near-ties may flip a pixel
    pad = np.pad(labels, reach, mode="edge")
    allowed = np.stack(
        [
            pad[reach + dy : reach + dy + h, reach + dx : reach + dx + w]
            for dy in (-reach, 0, reach)
            for dx in (-reach, 0, reach)
        ]
    )
    assert np.all((allowed == ours[None]).any(0))
    eager = np.asarray(sp.slic_step(jnp.asarray(lab), jnp.asarray(labels), k, step, 10.0, reach))
    np.testing.assert_array_equal(eager, ours)


def test_track_reach_closed_form():
    assert [sp.track_reach(s) for s in (1, 2, 4, 6, 7, 8, 20, 40)] == [1, 1, 2, 3, 3, 3, 3, 3]


def test_segment_centres_vs_numpy():
    rng = np.random.default_rng(1)
    lab = rng.normal(0, 1, (9, 11, 3)).astype(np.float32)
    labels = rng.integers(0, 6, (9, 11)).astype(np.int32)
    labels[labels == 4] = 5
    c, n = sp.segment_centres(jnp.asarray(lab), jnp.asarray(labels), 7)
    yy, xx = np.mgrid[0:9, 0:11]
    for j in range(7):
        m = labels == j
        assert float(n[j]) == m.sum()
        if m.any():
            ref = [*lab[m].mean(0), yy[m].mean(), xx[m].mean()]
            np.testing.assert_allclose(np.asarray(c[j]), ref, atol=1e-5)
        else:
            np.testing.assert_array_equal(np.asarray(c[j]), 0.0)


def test_shifted_is_clamped_indexing():
    a = np.arange(5 * 7).reshape(5, 7)
    p = jnp.pad(jnp.asarray(a), 3, mode="edge")
    for dy, dx in ((-3, 2), (0, 0), (3, -1), (2, 3)):
        ys = np.clip(np.arange(5) + dy, 0, 4)
        xs = np.clip(np.arange(7) + dx, 0, 6)
        np.testing.assert_array_equal(np.asarray(sp.shifted(p, 3, dy, dx)), a[ys][:, xs])


def test_working_rgb_is_the_block_mean():
    rgb = np.random.default_rng(2).random((20, 30, 3)).astype(np.float32)
    np.testing.assert_array_equal(sp.working_rgb(rgb), rgb)
    block = rgb.reshape(10, 2, 15, 2, 3).mean((1, 3))  # area average of 2 x 2 blocks
    np.testing.assert_allclose(sp.working_rgb(rgb, 2), block, atol=1e-6)
    u8 = np.round(rgb * 255).astype(np.uint8)
    np.testing.assert_allclose(
        sp.working_rgb(u8, 2), sp.working_rgb(u8 / np.float32(255), 2), atol=1e-6
    )
    assert sp.working_rgb(rgb[:19, :29], 2).shape == (10, 15, 3)  # rounded up
    with pytest.raises(ValueError):
        sp.working_rgb(rgb[..., 0])
    with pytest.raises(ValueError):
        sp.working_shape(10, 10, 0)


def test_upsample_labels_vs_kron():
    a = np.arange(12).reshape(3, 4).astype(np.int32)
    up = np.kron(a, np.ones((2, 2), np.int32))
    np.testing.assert_array_equal(np.asarray(sp.upsample_labels(jnp.asarray(a), 6, 8, 2)), up)
    np.testing.assert_array_equal(
        np.asarray(sp.upsample_labels(jnp.asarray(a), 5, 7, 2)), up[:5, :7]
    )
    np.testing.assert_array_equal(np.asarray(sp.upsample_labels(jnp.asarray(a), 3, 4, 1)), a)


def _regions(h, w, scale):
    """Piecewise-constant test image (three colour regions, boundaries on multiples of
    ``scale``) and its region map."""
    region = np.where(np.arange(h)[:, None] >= 30 * scale // 1, 2, 0) * np.ones((1, w), int)
    region = np.where((region == 0) & (np.arange(w)[None, :] >= 28 * scale), 1, region).astype(int)
    colours = np.array([[0.2, 0.6, 0.2], [0.9, 0.1, 0.1], [0.1, 0.2, 0.9]], np.float32)
    return colours[region], region


def test_segment_first_at_working_scale_respects_regions():
    """SLIC on the half-size image, labels repeated to full size: every segment stays inside
    one colour region, all ids in range, and the full map is the repeated working map."""
    img, region = _regions(96, 128, 2)
    small = jnp.asarray(sp.working_rgb(img, 2))
    # step 4 working px at scale 2 on 96x128: the program test_tracker_at_working_scale_two's
    # MotionTracker compiles (one compile for the module)
    gh, gw = sp.grid_shape(48, 64, 4)
    work, full = sp.segment_first(small, gh * gw, 4, 10.0, 6, 2, 96, 128)
    work, full = np.asarray(work), np.asarray(full)
    assert work.shape == (48, 64) and full.shape == (96, 128)
    np.testing.assert_array_equal(full, np.kron(work, np.ones((2, 2), np.int32)))
    assert full.min() >= 0 and full.max() < gh * gw
    for j in np.unique(full):
        assert len(np.unique(region[full == j])) == 1
    # compact: no segment grows beyond four seed cells
    assert np.bincount(work.ravel(), minlength=gh * gw).max() <= 4 * 16


def test_segment_track_follows_a_moving_block():
    """A block moved by 4 working px: the tracked labels move with it (ids kept) and still
    respect the new image's regions. Working 48x64 at step 4, full size 96x128 (scale 2):
    the programs test_tracker_at_working_scale_two's MotionTracker compiles."""
    h, w, step = 48, 64, 4
    img = np.full((h, w, 3), 0.3, np.float32)
    img[16:32, 16:32] = [0.9, 0.2, 0.1]
    img2 = np.full((h, w, 3), 0.3, np.float32)
    img2[16:32, 20:36] = [0.9, 0.2, 0.1]
    k = 12 * 16
    work, _ = sp.segment_first(jnp.asarray(img), k, step, 10.0, 6, 2, 2 * h, 2 * w)
    flow = np.zeros((h, w, 2), np.float32)
    flow[16:32, 16:32, 0] = 4.0
    w2, full2 = sp.segment_track(
        work, jnp.asarray(flow), jnp.asarray(img2), k, step, 10.0, 2, 2, 2 * h, 2 * w
    )
    w2 = np.asarray(w2)
    np.testing.assert_array_equal(np.asarray(full2), np.kron(w2, np.ones((2, 2), np.int32)))
    inside = set(np.unique(np.asarray(work)[16:32, 16:32]))
    assert set(np.unique(w2[16:32, 20:36])) == inside
    assert not (set(np.unique(w2[:, :20])) & inside)  # the wake went to the background


def _dominant_reference(flow):
    """Cauchy IRLS (scale 1 px, 3 reweightings from the mean) over every 4th row and column,
    in float64 by numpy."""
    sub = flow[::4, ::4].reshape(-1, 2).astype(np.float64)
    m = sub.mean(0)
    for _ in range(3):
        wt = 1.0 / (1.0 + ((sub - m) ** 2).sum(1))
        m = (sub * wt[:, None]).sum(0) / wt.sum()
    return m


def _priority_reference(flow):
    """|f - dominant motion| in quarter px, clipped at 64 px: the occlusion priority."""
    rel = np.sqrt(((flow.astype(np.float64) - _dominant_reference(flow)) ** 2).sum(-1))
    return np.round(np.clip(rel, 0, 64) * 4).astype(np.int64)


def _splat_reference(labels, flow):
    """Loop version of the splat: every target keeps the source of highest priority (ties:
    the later source in row-major order); a hole takes, among the splatted pixels 1..8 px
    right/left/down/up, the nearest of those within 1 px (4 levels) of the lowest priority;
    the rest the backward lookup."""
    h, w = labels.shape
    prio = _priority_reference(flow)
    best = {}
    for y in range(h):
        for x in range(w):
            tx, ty = int(np.round(x + flow[y, x, 0])), int(np.round(y + flow[y, x, 1]))
            if 0 <= tx < w and 0 <= ty < h:
                key = (prio[y, x], y * w + x)
                best[ty, tx] = max(best.get((ty, tx), key), key)
    filled = dict(best)
    for y in range(h):
        for x in range(w):
            if (y, x) in best:
                continue
            cands = []  # in order of distance, then right, left, down, up
            for d in range(1, 9):
                for dy, dx in ((0, d), (0, -d), (d, 0), (-d, 0)):
                    k = best.get((min(max(y + dy, 0), h - 1), min(max(x + dx, 0), w - 1)))
                    if k is not None:
                        cands.append(k)
            if cands:
                pmin = min(k[0] for k in cands)
                filled[y, x] = next(k for k in cands if k[0] <= pmin + 4)
    best = filled
    out = np.empty((h, w), np.int64)
    for y in range(h):
        for x in range(w):
            if (y, x) in best:
                src = best[y, x][1]
                out[y, x] = labels[src // w, src % w]
            else:
                sx = min(max(int(np.round(x - flow[y, x, 0])), 0), w - 1)
                sy = min(max(int(np.round(y - flow[y, x, 1])), 0), h - 1)
                out[y, x] = labels[sy, sx]
    return out


def test_dominant_motion_ignores_a_moving_minority():
    """A still background with 0.2 px noise and a quarter of the pixels moving 6 px: the
    robust estimate stays within 0.1 px of the background (the mean is 1.5 px off), and
    equals the float64 loop; the priority equals numpy's away from rounding ties."""
    rng = np.random.default_rng(7)
    flow = rng.normal(0.0, 0.2, (40, 48, 2)).astype(np.float32)
    flow[:20, :24] += np.float32([6.0, 0.0])
    m = np.asarray(dominant_motion(jnp.asarray(flow)))
    np.testing.assert_allclose(m, _dominant_reference(flow), atol=1e-4)
    assert np.abs(m).max() < 0.1 and flow[::4, ::4, 0].mean() > 1.4
    flow[0, 0] = [500.0, 0.0]  # clipped at 64 px
    ours = np.asarray(motion_priority(jnp.asarray(flow)))
    ref = _priority_reference(flow)
    assert np.mean(ours == ref) > 0.99 and np.abs(ours - ref).max() <= 1
    assert ours[0, 0] == 256


def test_splat_labels_vs_loop():
    """A block moved right by 5 px over a still background whose columns in front of it
    move out of the image (an unambiguous wake wider than the fill reach), and a random flow
    with many collisions and holes: the jitted splat equals the loop."""
    h, w = 16, 24
    labels = (np.arange(h)[:, None] // 4 * 6 + np.arange(w)[None, :] // 4).astype(np.int32)
    flow = np.zeros((h, w, 2), np.float32)
    flow[4:12, 14:19, 0] = 5.0  # moves onto background columns 19..23, which move away ...
    flow[4:12, 19:24, 1] = 20.0  # ... out of the image (dropped)
    ours = np.asarray(splat_labels(jnp.asarray(labels), jnp.asarray(flow)))
    np.testing.assert_array_equal(ours, _splat_reference(labels, flow))
    rng = np.random.default_rng(8)
    flow = np.round(rng.normal(0, 2.5, (h, w, 2))).astype(np.float32)  # no rounding ties
    ours = np.asarray(splat_labels(jnp.asarray(labels), jnp.asarray(flow)))
    np.testing.assert_array_equal(ours, _splat_reference(labels, flow))


@pytest.mark.parametrize("vel", [(3, 0), (-3, 0), (0, 3), (0, -3), (2, -2)])
def test_splat_moving_block_occludes_and_leaves_background_wake(vel):
    """A labelled block moving 3 px over a still labelled background, in every direction:
    the block's labels cover its whole new footprint (it occludes the background) and its
    wake gets background labels (disocclusion reveals what is behind). The plain scatter let
    the background win whenever the block moved right or down, and the fixed right-first
    fill put the block's own labels into the wake of a block moving right."""
    h, w = 40, 48
    labels = (np.arange(h)[:, None] // 8 * 6 + np.arange(w)[None, :] // 8).astype(np.int32)
    block = np.zeros((h, w), bool)
    block[12:28, 16:32] = True
    labels[block] += 100  # block ids are 100 + ...
    flow = np.zeros((h, w, 2), np.float32)
    flow[block] = vel
    moved = np.roll(block, (vel[1], vel[0]), axis=(0, 1))
    ours = np.asarray(splat_labels(jnp.asarray(labels), jnp.asarray(flow)))
    np.testing.assert_array_equal(ours[moved], np.roll(labels, (vel[1], vel[0]), (0, 1))[moved])
    wake = block & ~moved
    assert np.all(ours[wake] < 100)
    np.testing.assert_array_equal(ours[~block & ~moved], labels[~block & ~moved])


def test_warp_and_points_vs_numpy_indexing():
    rng = np.random.default_rng(3)
    labels = rng.integers(0, 50, (10, 13)).astype(np.int32)
    flow = rng.normal(0, 3, (10, 13, 2)).astype(np.float32)
    yy, xx = np.mgrid[0:10, 0:13]
    sx = np.clip(np.round(xx - flow[..., 0]).astype(int), 0, 12)
    sy = np.clip(np.round(yy - flow[..., 1]).astype(int), 0, 9)
    np.testing.assert_array_equal(
        np.asarray(warp_labels(jnp.asarray(labels), jnp.asarray(flow))), labels[sy, sx]
    )
    pts = rng.uniform(-3, 16, (30, 2)).astype(np.float32)
    ref = labels[
        np.clip(np.round(pts[:, 1]).astype(int), 0, 9),
        np.clip(np.round(pts[:, 0]).astype(int), 0, 12),
    ]
    np.testing.assert_array_equal(
        np.asarray(labels_at_points(jnp.asarray(labels), jnp.asarray(pts))), ref
    )


@pytest.mark.parametrize("scale", [1, 2, 4])
def test_dense_from_grid_is_exact_for_affine_flow(scale):
    """Bilinear interpolation reproduces an affine field away from the border, at full
    (scale 1) or working resolution (flow in working px at working pixel centres)."""
    H, W, step = 64, 96, 8
    pts = fm.grid_points(H, W, step)
    A = np.array([[0.02, -0.01], [0.015, 0.03]], np.float32)
    t = np.array([1.5, -2.0], np.float32)
    flow = pts @ A.T + t
    valid = np.ones(len(pts), bool)
    valid[3 * 12 + 5] = False  # interior; filled by a symmetric average: exact for affine
    dense = fm.dense_from_grid(np.where(valid[:, None], flow, 0), valid, H, W, step, scale)
    h, w = -(-H // scale), -(-W // scale)
    assert dense.shape == (h, w, 2) and dense.dtype == np.float32
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    full = np.stack([scale * xx + (scale - 1) / 2, scale * yy + (scale - 1) / 2], -1)
    ref = (full @ A.T + t) / scale
    m = step // scale  # one grid cell inside the border
    np.testing.assert_allclose(dense[m:-m, m:-m], ref[m:-m, m:-m], atol=0.03 / scale)
    with pytest.raises(ValueError):
        fm.dense_from_grid(flow, valid, H, W, 6, 4)


def test_to_gray_u8_matches_round_clip():
    x = np.random.default_rng(4).uniform(-0.2, 1.2, (13, 17, 3)).astype(np.float32)
    x[0, 0] = 0.5 / 255  # a rounding tie
    ref = cv2.cvtColor(np.clip(np.round(x * 255), 0, 255).astype(np.uint8), cv2.COLOR_RGB2GRAY)
    np.testing.assert_array_equal(fm.to_gray_u8(x), ref)
    u8 = (x.clip(0, 1) * 255).astype(np.uint8)
    np.testing.assert_array_equal(fm.to_gray_u8(u8), cv2.cvtColor(u8, cv2.COLOR_RGB2GRAY))


def _texture(h, w, seed):
    rng = np.random.default_rng(seed)
    return cv2.GaussianBlur(rng.integers(0, 256, (h, w)).astype(np.uint8), (5, 5), 1.2)


def test_grid_flow_vs_opencv_and_known_shift():
    g0 = _texture(72, 96, 5)
    M = np.float32([[1, 0, 2.5], [0, 1, -1.5]])
    g1 = cv2.warpAffine(g0, M, (96, 72), borderMode=cv2.BORDER_REFLECT)
    for cfg in (fm.FlowConfig(step=8), fm.FlowConfig(step=8, window=9, levels=2),
                fm.FlowConfig(step=8, iters=1)):  # fmt: skip
        pts, flow, valid = fm.grid_flow(g0, g1, cfg)
        nxt, st, _ = cv2.calcOpticalFlowPyrLK(
            g0,
            g1,
            pts[:, None, :],
            None,
            winSize=(cfg.window, cfg.window),
            maxLevel=cfg.levels,
            criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, cfg.iters, 0.03),
            minEigThreshold=cfg.min_eig,
        )
        ok = st.ravel().astype(bool)
        assert np.array_equal(valid, ok & np.all((nxt[:, 0] >= 0) & (nxt[:, 0] <= [95, 71]), 1))
        np.testing.assert_allclose(flow[valid], (nxt[:, 0] - pts)[valid], atol=1e-6)
        interior = valid & (pts[:, 0] > 12) & (pts[:, 0] < 84) & (pts[:, 1] > 12) & (pts[:, 1] < 60)
        np.testing.assert_allclose(np.median(flow[interior], 0), [2.5, -1.5], atol=0.05)
        if cfg.iters == 1:  # the cap reaches OpenCV: one step per level is not 20 steps
            full = fm.grid_flow(g0, g1, fm.FlowConfig(step=8))[1]
            assert np.abs(flow[valid] - full[valid]).max() > 1e-3


def test_tracker_at_working_scale_two(tmp_path):
    """The whole M-L run with the superpixels on the half-size frame (forced scale 2 on a
    tiny video): full-size label maps repeated from the working ones, the segment count of the
    working grid, and the pushed object still the most probable region."""
    from jaxcr.io.motion_dataset import load_motion_dataset
    from jaxcr.motion.pipeline import MotionConfig, MotionTracker
    from jaxcr.motion.run import run_motion
    from jaxcr.synth.motion_scenes import generate_motion_video

    d = tmp_path / "push"
    generate_motion_video(d, "pushed_static", seed=0, size=(128, 96), n_frames=8, speed_px=10)
    ds = load_motion_dataset(d)
    # flow step 4: the frame_update program of test_motion_pipeline / _cli_baseline / _batch
    # (same frame size, segment count and flags; run cache), not one of its own
    cfg = MotionConfig(
        superpixel_step=8, superpixel_scale=2, models=("translation",), flow=fm.FlowConfig(step=4)
    )
    res = run_motion(ds, cfg)
    assert res.labels_eval.shape == (96, 128)
    work = res.labels_eval[::2, ::2]
    np.testing.assert_array_equal(res.labels_eval, np.kron(work, np.ones((2, 2), np.int32)))
    assert res.labels_eval.max() < 12 * 16  # the 4-px working grid of a 64 x 48 frame
    gt = ds.mask(res.eval_frame)
    pm = res.maps["translation"]
    assert pm[gt].mean() > pm[~gt].mean() + 0.1
    tracker = MotionTracker(cfg, next(ds.frames())[1])
    assert (tracker.scale, tracker.sp_step, tracker.n_segments) == (2, 4, 12 * 16)
    # the auto default keeps a 128-px frame at full resolution
    assert MotionTracker(MotionConfig(superpixel_step=8), next(ds.frames())[1]).scale == 1
