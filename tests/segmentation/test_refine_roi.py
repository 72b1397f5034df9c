"""Tracked frames on a region of interest (jaxcr.segmentation.refine, ``roi``; docs/decisions.md
S21): with the local outside mean (S3) the band energy computed on a tile-aligned window of the
image, with the whole image's colour variance, equals the whole image's; the window's size
buckets; the border test that sends a frame back to the whole image; the fall-backs; one
tracked sequence on a region.

One refinement program is compiled here (the region's, 160x120, last test); the energy pieces
run through the shared jitted helpers of tests/helpers/jitted.py (small images), the
fall-backs with stubs.
"""

import jax.numpy as jnp
import numpy as np
import pytest

import jaxcr.segmentation.refine as refine
from jaxcr.errors import InputError
from jaxcr.segmentation.energy import Weights, chan_vese_energy
from jaxcr.segmentation.silhouette import Band, TileGrid, project_tube
from tests.helpers.jitted import integrate_centreline, prepare_region_data, select_band
from tests.segmentation.test_energy import _scene

W, H = 96, 72
EPS32 = float(np.finfo(np.float32).eps)


def _shifted(tube, c0, r0):
    return refine.TubeImage(
        tube.ax - c0, tube.ay - r0, tube.bx - c0, tube.by - r0, tube.ra, tube.rb, tube.valid
    )


def test_roi_energy_equals_full_image_energy():
    """Region data of a tile-aligned window equal the whole image's restricted to it (same
    per-tile sums), and the local band energy with the whole image's variance is the same J.

    Tolerance: the window's data are centred on the window's mean colour instead of the
    image's, and the band's tiles may be gathered in another order (ties of the band's
    distance order), so J differs by float32 summation order only: the band has k * 64 = 1536
    pixels, and the ordered sums of at most that many non-negative terms differ by at most
    1536 eps relative (Higham's bound); the e = S2 - |S1|^2 / S0 forms lose a further
    S2 / e <= 10 here (a random image in [0, 1]: variance 1/12 against a mean square of 1/3,
    times the 3 channels' spread): rtol = 10 * 1536 * eps = 1.8e-3, atol on the per-tile sums
    64 terms in [0, 3] * 64 eps.
    """
    cl, cam = _scene()
    rng = np.random.default_rng(5)
    img = jnp.asarray(rng.random((H, W, 3)).astype(np.float32))
    bg = jnp.asarray(rng.random((H, W)) < 0.2)
    tube = project_tube(cam, cl)
    full = prepare_region_data(img, bg, 0, 8)
    r0, c0, h, w = 0, 8, 56, 80  # tile-aligned window around the tube (its top the image's)
    k = 24
    part = prepare_region_data(img[r0 : r0 + h, c0 : c0 + w], bg[r0 : r0 + h, c0 : c0 + w], 0, 8)
    rows = np.arange(r0 // 8, (r0 + h) // 8)
    cols = np.arange(c0 // 8, (c0 + w) // 8)
    idx = (rows[:, None] * full.grid.cols + cols[None]).ravel()
    atol = 64 * 3.0 * 64 * EPS32
    np.testing.assert_allclose(part.tile_w, np.asarray(full.tile_w)[idx], atol=atol)
    np.testing.assert_allclose(part.tile_b, np.asarray(full.tile_b)[idx], atol=atol)
    var = float(refine._image_variance(img, bg))
    np.testing.assert_allclose(
        var, float(full.total_s2 / full.total_w), rtol=W * H * EPS32
    )  # two orders of one sum of W * H terms
    J = {}
    for name, data, t in (("full", full, tube), ("roi", part, _shifted(tube, c0, r0))):
        band = select_band(t, data.grid, k, 8)
        if name == "full":  # the premise: the whole image's band lies in the window
            row, col = np.divmod(np.asarray(band.tiles), data.grid.cols)
            assert row.max() < (r0 + h) // 8 and col.min() >= c0 // 8 and col.max() < (c0 + w) // 8
        J[name] = float(
            chan_vese_energy(
                t, band, data, 0.0, Weights(), 0.8, jnp.asarray(500.0), local=True,
                var=jnp.asarray(var),
            )[0]
        )  # fmt: skip
    np.testing.assert_allclose(J["roi"], J["full"], rtol=10 * k * 64 * EPS32)


def test_roi_shape_buckets():
    """Extent + 2 margins rounded up to eighths of the image (whole tiles); None when the
    region would be the image. Integer arithmetic: exact."""
    assert refine.roi_shape((145.0, 308.0), (480, 640)) == (320, 480)
    assert refine.roi_shape((100.0, 100.0), (720, 1280), margin=32.0) == (192, 320)
    assert refine.roi_shape((400.0, 600.0), (480, 640)) is None
    # an image side that is not a multiple of 8 tiles: the step stays whole tiles
    assert refine.roi_shape((10.0, 10.0), (120, 160), margin=8.0) == (32, 48)


def test_roi_pays_from_the_image_and_region_areas():
    """``roi_pays`` (``jaxcr segment --roi auto``): every camera at least ROI_AUTO_MIN_PIXELS
    (2 x 640 x 480) pixels and a region of at most ROI_AUTO_MAX_FRACTION (1/4) of each image;
    integer products against exact binary fractions: no rounding."""
    from types import SimpleNamespace as Cam

    big, small = Cam(height=720, width=1280), Cam(height=480, width=640)
    assert refine.ROI_AUTO_MIN_PIXELS == 2 * 640 * 480 and refine.ROI_AUTO_MAX_FRACTION == 0.25
    assert refine.roi_pays(big, (288, 480))  # S21's window: 15 %
    assert refine.roi_pays(big, (360, 640))  # exactly a quarter
    assert not refine.roi_pays(big, (368, 640))
    assert not refine.roi_pays(big, (576, 800))  # the orthogonal sets' windows (S28)
    assert not refine.roi_pays(big, None)
    assert not refine.roi_pays(small, (96, 160))  # a small image: never
    assert not refine.roi_pays((big, small), (96, 160))


def test_segmenter_roi_modes(monkeypatch):
    """``jaxcr segment --roi``'s choice per chunk (``Segmenter._roi_arg``), with
    ``tracking_roi`` replaced by given windows (no program compiled): "on" lets
    ``refine_sequence`` size each chunk's region; "auto" takes the window only where
    ``roi_pays``, grown to the run's largest; "off" and small images never."""
    from types import SimpleNamespace as NS

    from jaxcr.segmentation.batch import Segmenter

    big, small = NS(height=720, width=1280), NS(height=480, width=640)
    windows = iter([(288, 480), (320, 400), (480, 800)])
    monkeypatch.setattr(refine, "tracking_roi", lambda bases, cams, config: next(windows))

    def seg(mode, cam):
        return NS(roi=mode, cameras=(cam,), config=refine.RefineConfig(), _roi_run=None)

    auto = seg("auto", big)
    assert Segmenter._roi_arg(auto, None) == (288, 480)
    assert Segmenter._roi_arg(auto, None) == (320, 480)  # the run's largest on each axis
    assert Segmenter._roi_arg(auto, None) is None  # 480 x 800: over a quarter of the image
    assert Segmenter._roi_arg(seg("on", small), None) == "auto"
    assert Segmenter._roi_arg(seg("off", big), None) is None
    assert Segmenter._roi_arg(seg("auto", small), None) is None  # tracking_roi not called


def test_band_border_test():
    """A band tile in the two rings next to an inner border of the window fails the test; at
    a border that is the image's own it does not. Exact (integer tile arithmetic)."""
    grid = TileGrid(64, 64, 8)  # 8 x 8 tiles
    size = (480, 640)

    def band(tiles):
        t = jnp.asarray(tiles, jnp.int32)
        return Band(t, jnp.zeros((len(tiles), 1), jnp.int32), jnp.zeros(64, bool), True)

    centre = band([27, 28, 35, 36])
    assert bool(refine._band_clear_of_border(centre, grid, 80, 80, size))
    ring = band([27, 11])  # row 1 (the second ring from the top), column 3
    assert not bool(refine._band_clear_of_border(ring, grid, 80, 80, size))
    # the window at the image's top: the top border is the image's
    assert bool(refine._band_clear_of_border(ring, grid, 0, 80, size))
    right = band([30])  # column 6 of 8
    assert not bool(refine._band_clear_of_border(right, grid, 80, 80, size))
    assert bool(refine._band_clear_of_border(right, grid, 80, 640 - 64, size))


def test_falls_back_to_the_whole_image(monkeypatch):
    """refine_frame_jit with ``roi``: a region result whose bands reach the border is
    discarded and the whole image is refined (the per-frame program); one that fits is
    returned. Stubbed programs: the logic only."""
    calls = []

    def roi_prog(*args):
        calls.append("roi")
        return "roi result", jnp.asarray(fit)

    def full_prog(*args):
        calls.append("full")
        return "full result"

    monkeypatch.setattr(refine, "_refine_frame_roi_jit", roi_prog)
    monkeypatch.setattr(refine, "_refine_frame_jit", full_prog)
    monkeypatch.setattr(refine.eqx, "tree_at", lambda f, r, v: r)
    cl, cam = _scene()
    img, bg = jnp.zeros((H, W, 3)), jnp.zeros((H, W), bool)
    cfg = refine.RefineConfig().warm()
    for fit, want in ((True, ["roi"]), (False, ["roi", "full"])):
        calls.clear()
        out = refine.refine_frame_jit(cl, cam, img, bg, cfg, roi=(48, 64))
        assert calls == want
        assert out == ("roi result" if fit else "full result")


def test_roi_needs_a_local_one_level_config():
    """The region changes the energy unless the outside mean is local and the schedule is one
    level at full resolution: other configs are refused (tracking_roi returns None for them)."""
    n = 9
    s = jnp.linspace(0.0, 0.12, n)
    R0 = jnp.array([[0.0, 0, 1], [0, 1, 0], [-1, 0, 0]])
    cl = integrate_centreline(
        s, jnp.tile(jnp.array([8.0, 3.0, 0.0]), (n - 1, 1)), jnp.full(n, 4e-3),
        jnp.array([-0.05, 0.0, 0.0]), R0,
    )  # fmt: skip
    _, cam = _scene()
    img, bg = jnp.zeros((H, W, 3)), jnp.zeros((H, W), bool)
    for cfg in (refine.RefineConfig(), refine.RefineConfig(local=False).warm()):
        with pytest.raises(InputError, match="roi"):
            refine._refine_frame(
                cl, cam, img, bg, cfg, None, True, None, None, steps=None, roi=(48, 64)
            )


def test_sequence_falls_back_to_the_whole_images(monkeypatch):
    """refine_sequence with ``roi``: when any frame's bands reach the border, the whole
    sequence runs again without a region (the program of before); otherwise the region's
    results are returned. Stubbed programs: the logic only."""
    calls = []

    def prog(*args):
        calls.append(len(args))
        if len(args) == 12:  # with a region: the results and a flag per frame
            return "roi results", jnp.asarray([True, fit])
        return "full results"

    monkeypatch.setattr(refine, "_refine_sequence_jit", prog)
    monkeypatch.setattr(refine.eqx, "tree_at", lambda f, r, v: r)
    monkeypatch.setattr(refine.jax, "block_until_ready", lambda x: x)
    cl, cam = _scene()
    bases = refine.jax.tree.map(lambda x: jnp.stack([x, x]), cl)
    imgs, bgs = jnp.zeros((2, H, W, 3)), jnp.zeros((2, H, W), bool)
    for fit, want in ((True, [12]), (False, [12, 11])):
        calls.clear()
        out = refine.refine_sequence(bases, cam, imgs, bgs, roi=(48, 64))
        assert calls == want
        assert out == ("roi results" if fit else "full results")
    with pytest.raises(InputError, match="roi"):
        refine.refine_sequence(bases, cam, imgs, bgs, roi="everywhere")


def test_sequence_on_a_region_tracks_the_tube():
    """The suite's canonical scene (tests/helpers/refine_scene.py, 160x120) tracked by a
    one-level local config on a 96x144 window (tracking_roi, 32 px margin): the region
    program runs on both frames without falling back, the masks come back at full size, and
    the tube is found as on the whole image. Measured: IoU to the truth 0.912 / 0.930 with the
    region and with the whole images (frame 0 bit-identical masks, frame 1 mask IoU 0.977
    between the two: the energies agree to float rounding, test above, and the solver's step
    decisions amplify rounding, decisions S21); the convergence tests' threshold for this
    scene, IoU > 0.85, is kept. One compiled program (the region's; 160x120)."""
    from jaxcr.segmentation.metrics import iou
    from tests.helpers import refine_scene
    from tests.helpers.tube_render import tube_frames

    true = [
        np.array([[0.15, -0.05, 0.0], [0.0, 0.0, 0.0]], np.float32),
        np.array([[-0.12, 0.06, 0.0], [0.0, 0.0, 0.0]], np.float32),
    ]
    base, cam = refine_scene.base(), refine_scene.camera()
    frames = tube_frames(base, cam, true, (refine_scene.W, refine_scene.H))
    cfg = refine.RefineConfig(
        n_coeffs=3, levels=(0,), steps=(30,), outer=(2,), tau=(0.8,), band_tiles=40,
        min_tiles=24, g_reg=0.5, camera_correction=False,
    )  # fmt: skip
    bases = refine.jax.tree.map(lambda *x: jnp.stack(x), base, base)
    roi = refine.tracking_roi(bases, cam, config=cfg, margin=32.0)
    assert roi == (96, 144)
    calls = []
    prog = refine._refine_sequence_jit

    def spy(*args):
        out = prog(*args)
        calls.append(None if len(args) == 11 else np.asarray(out[1]))
        return out

    imgs = jnp.stack([f["img"] for f in frames])
    bgs = jnp.stack([f["bg"] for f in frames])
    try:
        refine._refine_sequence_jit = spy
        r = refine.refine_sequence(bases, cam, imgs, bgs, cfg, roi=roi)
    finally:
        refine._refine_sequence_jit = prog
    assert len(calls) == 1 and calls[0].tolist() == [True, True]
    assert r.masks[0].shape == (2, refine_scene.H, refine_scene.W)
    for k, f in enumerate(frames):
        assert float(iou(r.masks[0][k], f["mask"])) > 0.85
