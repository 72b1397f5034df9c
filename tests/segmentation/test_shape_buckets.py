"""Shape buckets (jaxcr.segmentation.buckets, refine/uncertainty ``sizes``; docs/decisions.md
S29): the ladder's rule; padding at the bottom/right weighs nothing, so the pyramid, the band
selection, the silhouette area and the band energy of a padded image equal the unpadded
image's (the reference: the unpadded path, unchanged); and a refined batch padded into a
larger shape finds the same tube.

Small images: a 93x69 real image (odd sizes at levels 1 and 2, partial tiles) padded into
128x96; two small programs (padded and unpadded level energies). The end-to-end refinement
(the suite's canonical 160x120 scene, whose unpadded program test_refine compiles) is marked
slow.
"""

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxcr.segmentation.refine as refine
from jaxcr.segmentation import buckets
from jaxcr.segmentation.energy import chan_vese_energy, pyramid
from jaxcr.segmentation.silhouette import level_tube_padded, project_tube, select_band
from tests.segmentation.test_energy import _scene

EPS32 = float(np.finfo(np.float32).eps)
RW, RH = 93, 69  # the real image
PW, PH = 128, 96  # the padded arrays


def test_ladder_rule():
    """Common sides are their own bucket; other sizes go to the next rung; rungs are multiples
    of 8 (the default tile) at most 1.25x apart from 64 px up, so a side grows by < 25 %."""
    for h, w in ((240, 320), (480, 640), (720, 1280), (1080, 1920), (2160, 3840)):
        assert buckets.bucket_shape(h, w) == (h, w)
        assert buckets.padded_fraction(h, w) == 0.0
    assert buckets.bucket_shape(450, 600) == (480, 640)
    assert buckets.bucket_shape(700, 1280) == (720, 1280)
    assert buckets.bucket_shape(72, 96) == (80, 96)
    assert buckets.bucket_shape(5000, 4097) == (5120, 5120)
    assert all(s % 8 == 0 for s in buckets.LADDER)
    assert list(buckets.LADDER) == sorted(set(buckets.LADDER))
    for n in range(64, 8193):
        b = buckets.bucket_side(n)
        assert n <= b < 1.25 * n or b == n, n
    padded = buckets.pad_frames(np.ones((2, 3, 5, 3)), (8, 8))
    assert padded.shape == (2, 8, 8, 3) and padded[:, :3, :5].all() and not padded[:, 3:].any()
    with pytest.raises(ValueError):
        buckets.pad_frames(np.ones((1, 9, 5)), (8, 8))


def _valid(sizes):
    return (jnp.arange(PH)[:, None] < sizes[0]) & (jnp.arange(PW)[None, :] < sizes[1])


CFG = refine.RefineConfig(
    levels=(2, 1, 0), steps=(1, 1, 1), outer=(1, 1, 1), tau=(1.0, 0.8, 0.5), band_tiles=64,
    min_tiles=16, local=False, camera_correction=False,
)  # fmt: skip


@eqx.filter_jit
def _level_energies(cam, img, bg, cl, sizes):
    """What a solve of refine_frame sees at each level: the pyramid, the levels' tables (data
    on the finest grid, tile_ok, k_active), the band and J (the whole image's outside mean:
    the image totals count), with the silhouette area of the real image."""
    real = None if sizes is None else (sizes[0], sizes[1])
    pyr = pyramid(img, bg, 3, None if sizes is None else _valid(sizes))
    tables = refine._level_tables([pyr], CFG, cl.p.shape[0] - 1, img.dtype, None, None,
                                  None if sizes is None else (real,))  # fmt: skip
    tube = project_tube(cam, cl, size=real)
    area = refine._tube_area(tube, cam, real)
    out = []
    for li in range(3):
        lv = jax.tree.map(lambda x, li=li: x[li], tables)
        d = lv.datas[0]
        t = level_tube_padded(tube, lv.level, CFG.seg_merge, lv.n_capsules)
        band = select_band(t, d.grid, lv.k_max[0], CFG.k_seg, lv.tile_ok[0], lv.k_active[0])
        J, terms = chan_vese_energy(t, band, d, 0.0, CFG.weights, lv.tau, area, CFG.local)
        out.append((J, terms["e_in"], terms["e_out"], terms["e_pen"], band.tiles, band.active))
    return area, pyr, out


def _tiles(tiles, active, cols):
    t = np.asarray(tiles)[np.asarray(active)]
    return {(int(i) // cols, int(i) % cols) for i in t}


def test_padding_weighs_nothing_in_pyramid_band_and_energy():
    """A 93x69 image padded into 128x96 (padding: random colours, half of it 'background')
    against the same image unpadded, at pyramid levels 2, 1, 0 (odd sizes 47x35 and 24x18,
    partial tiles): the levels' real pixels and weights are the same, the padding's weights
    are zero, the band holds the same tiles (by row and column), and J and the eq. 5 terms
    agree.

    Tolerances: the pyramid's 2x2 sums add exact zeros for the padding, so its real part is
    equal up to a reordering of four terms (4 eps relative). J and the terms are float32
    sums over the band (k tiles x 64 px) and over the whole image (the outside moments with
    ``local=False``: S2 - |S1|^2 / S0 over 93 x 69 = 6417 px), taken over arrays of another
    shape (another summation order): Higham's bound for a reordered sum of n non-negative
    terms, n eps relative, with n = 6417, and the e_out - e_out(empty) difference losing a
    further factor S2 / e (<= 10 for a random image, as in test_refine_roi): rtol = 10 * 6417
    * eps = 7.6e-3 on J's data term; the silhouette area is the same sum of the same capsules
    (equal up to 1 ulp)."""
    cl, cam0 = _scene()
    cam = dataclasses.replace(cam0, width=RW, height=RH)
    rng = np.random.default_rng(3)
    img = rng.random((PH, PW, 3)).astype(np.float32)
    bg = rng.random((PH, PW)) < 0.3
    area_u, pyr_u, lv_u = _level_energies(cam, jnp.asarray(img[:RH, :RW]),
                                          jnp.asarray(bg[:RH, :RW]), cl, None)  # fmt: skip
    cam_p, sizes = refine.bucket_cameras(cam, jnp.zeros((PH, PW, 3)), True)
    assert (cam_p[0].height, cam_p[0].width) == (PH, PW)
    assert np.asarray(sizes).tolist() == [[RH, RW]]
    area_p, pyr_p, lv_p = _level_energies(cam_p[0], jnp.asarray(img), jnp.asarray(bg), cl,
                                          sizes[0])  # fmt: skip
    np.testing.assert_allclose(float(area_p), float(area_u), rtol=2 * EPS32)
    for level, (pu, pp) in enumerate(zip(pyr_u, pyr_p, strict=True)):
        h, w = pu[1].shape
        assert (h, w) == (-(-RH // 2**level), -(-RW // 2**level))
        for a, b in zip(pu, pp, strict=True):
            np.testing.assert_allclose(np.asarray(b)[:h, :w], np.asarray(a), atol=4 * EPS32)
        for b in pp[1:]:  # the weights of the padding
            assert not np.asarray(b)[h:].any() and not np.asarray(b)[:, w:].any()
    cols_u = -(-RW // 8)
    cols_p = PW // 8
    for level, (u, p) in enumerate(zip(lv_u, lv_p, strict=True)):
        assert _tiles(u[4], u[5], cols_u) == _tiles(p[4], p[5], cols_p), level
        for a, b in zip(u[:4], p[:4], strict=True):
            np.testing.assert_allclose(float(b), float(a), rtol=10 * RW * RH * EPS32, atol=1e-6)


def test_projection_clamps_to_the_real_image():
    """A point far outside the image is clamped to the real image's box [-w, 2w] x [-h, 2h]
    (as a camera of the real size clamps it), not the padded camera's."""
    cl, cam0 = _scene()
    cam = dataclasses.replace(cam0, width=RW, height=RH)
    far = jax.tree.map(lambda x: x, cl)
    far = eqx.tree_at(lambda c: c.p, far, cl.p.at[0].set(jnp.array([-0.5, 0.4, 0.0])))
    t_real = project_tube(cam, far)
    t_pad = project_tube(dataclasses.replace(cam, width=PW, height=PH), far, size=(RH, RW))
    for f in ("ax", "ay", "bx", "by", "ra", "rb"):
        np.testing.assert_array_equal(np.asarray(getattr(t_pad, f)), np.asarray(getattr(t_real, f)))
    # the premise: clamped there (u beyond the real image's box, not the padded camera's)
    assert float(t_real.ax[0]) == -RW
    assert float(t_real.ay[0]) in (-RH, 2.0 * RH)


def test_bucket_cameras_refuses_small_arrays():
    from jaxcr.errors import InputError

    _, cam = _scene()
    with pytest.raises(InputError, match="smaller"):
        refine.bucket_cameras(cam, jnp.zeros((10, 10, 3)), True)
    assert refine.bucket_cameras(cam, jnp.zeros((10, 10, 3)), False)[1] is None


@pytest.mark.slow
def test_refine_batch_padded_finds_the_same_tube():
    """The suite's canonical scene (tests/helpers/refine_scene.py: 160x120, two levels, the
    whole image's outside mean), refine_batch on F = 2 frames unpadded (test_refine's
    program) and padded into 192x128 with ``shape_buckets``: the nominal masks and J are the
    same (no solve: float rounding of the image sums only, rtol 1e-5 as test_refine's
    two-program comparison), the masks are False on the padding, and the refined tubes agree.

    Tolerance of the refined shapes: the energies agree to float rounding (test above), but
    a solve's step and stop decisions amplify rounding (decisions S21: a region of interest,
    the same energy up to rounding, gave a mask IoU of 0.977 between the two runs; the
    Laplace covariance of this scene allows tip motions of ~0.9 px). Measured here: masks
    differing on 1 and 0 pixels, centrelines 1.1e-4 / 2.0e-4 m apart (0.07-0.13 px at the
    tube's depth), J 0.6 % / 0.35 % apart, the same steps. Asserted: IoU between the masks
    >= 0.97 (S21's figure), each mask's IoU to the truth > 0.85 (test_refine's threshold),
    projected centrelines within 0.5 px on average (a third of the tube's ~1.7 px radius),
    J within 2 %; the covariance at equal coefficients within 1e-4 relative."""
    from jaxcr.camera import project_xy
    from jaxcr.segmentation.metrics import iou
    from jaxcr.segmentation.uncertainty import shape_uncertainty_batch
    from tests.helpers.refine_scene import CFG as RCFG
    from tests.helpers.refine_scene import H, W
    from tests.helpers.tube_render import tube_frames
    from tests.segmentation.test_refine import TRUE_COEFFS, _base, _camera

    base, cam = _base(), _camera()
    frames = tube_frames(base, cam, TRUE_COEFFS, (W, H))
    bases = jax.tree.map(lambda *x: jnp.stack(x), base, base)
    imgs = np.stack([np.asarray(f["img"]) for f in frames])
    bgs = np.stack([np.asarray(f["bg"]) for f in frames])
    a = refine.refine_batch(bases, cam, jnp.asarray(imgs), jnp.asarray(bgs), RCFG, mode="map")
    shape = (128, 192)
    pi, pb = buckets.pad_frames(imgs, shape), buckets.pad_frames(bgs, shape, fill=True)
    b = refine.refine_batch(bases, cam, jnp.asarray(pi), jnp.asarray(pb), RCFG, mode="map",
                            shape_buckets=True)  # fmt: skip
    assert b.masks[0].shape == (2,) + shape
    for k, f in enumerate(frames):
        mb, nb = np.asarray(b.masks[0][k]), np.asarray(b.nominal_masks[0][k])
        assert not mb[H:].any() and not mb[:, W:].any() and not nb[H:].any()
        np.testing.assert_array_equal(nb[:H, :W], np.asarray(a.nominal_masks[0][k]))
        np.testing.assert_allclose(float(b.energy.total_nominal[k]),
                                   float(a.energy.total_nominal[k]), rtol=1e-5)  # fmt: skip
        ma = np.asarray(a.masks[0][k])
        assert float(iou(ma, mb[:H, :W])) >= 0.97
        assert float(iou(ma, f["mask"])) > 0.85 and float(iou(mb[:H, :W], f["mask"])) > 0.85
        u1, v1, _ = project_xy(cam, a.centreline.p[k])
        u2, v2, _ = project_xy(cam, b.centreline.p[k])
        assert float(jnp.mean(jnp.hypot(u1 - u2, v1 - v2))) < 0.5
        np.testing.assert_allclose(float(b.energy.total[k]), float(a.energy.total[k]), rtol=0.02)
    ua = shape_uncertainty_batch(bases, cam, jnp.asarray(imgs), jnp.asarray(bgs), RCFG,
                                 a.coeffs, a.camera_correction)  # fmt: skip
    ub = shape_uncertainty_batch(bases, cam, jnp.asarray(pi), jnp.asarray(pb), RCFG, a.coeffs,
                                 a.camera_correction, shape_buckets=True)  # fmt: skip
    for f in ("sigma_px", "sigma_depth", "tip"):
        np.testing.assert_allclose(np.asarray(getattr(ub, f)), np.asarray(getattr(ua, f)),
                                   rtol=1e-4)  # fmt: skip


def test_front_door_pads_to_each_cameras_bucket_and_crops_the_masks(monkeypatch):
    """``jcr.refine_batch(..., shape_buckets=True)``: each camera's frames reach the compiled
    solver padded at the bottom and right to that camera's bucket (images with 0, background
    masks with True, as ``jaxcr segment`` pads them), with ``shape_buckets=True``; the masks
    come back cropped to each camera's real size. The solver is replaced by a recorder (its
    padded answer is tested above); reference: NumPy slicing of the padded arrays."""
    import jaxcr as jcr
    from jaxcr.camera import Camera

    calls = {}

    class Out(eqx.Module):
        masks: tuple
        nominal_masks: tuple
        coeffs: jax.Array

    def fake(bases, cameras, images, backgrounds, config, *args, shape_buckets=False):
        calls.update(images=images, backgrounds=backgrounds, shape_buckets=shape_buckets)
        ms = tuple(jnp.ones(b.shape, bool) for b in backgrounds)
        return Out(ms, tuple(~m for m in ms), jnp.zeros((2, 3, 4)))

    def _cam(k, w, h):
        return Camera(K=k, dist=jnp.zeros(5), T_cam_robot=jnp.eye(4), width=w, height=h)

    monkeypatch.setattr(refine, "refine_batch", fake)
    k = jnp.array([[80.0, 0, 48], [0, 80, 36], [0, 0, 1]])
    cams = (_cam(k, RW, RH), _cam(k, 64, 48))
    rng = np.random.default_rng(0)
    imgs = (rng.random((2, RH, RW, 3), np.float32), rng.random((2, 48, 64, 3), np.float32))
    bgs = (rng.random((2, RH, RW)) > 0.5, rng.random((2, 48, 64)) > 0.5)
    out = jcr.refine_batch(None, cams, imgs, bgs, shape_buckets=True)
    assert calls["shape_buckets"] is True
    for c, im, bg, pim, pbg in zip(
        cams, imgs, bgs, calls["images"], calls["backgrounds"], strict=True
    ):
        shape = buckets.bucket_shape(c.height, c.width)
        assert pim.shape == (2, *shape, 3) and pbg.shape == (2, *shape)
        np.testing.assert_array_equal(np.asarray(pim)[:, : c.height, : c.width], im)
        np.testing.assert_array_equal(np.asarray(pbg)[:, : c.height, : c.width], bg)
        assert not np.asarray(pim)[:, c.height :].any() and np.asarray(pbg)[:, c.height :].all()
        assert not np.asarray(pim)[:, :, c.width :].any() and np.asarray(pbg)[:, :, c.width :].all()
    assert buckets.bucket_shape(RH, RW) != (RH, RW)  # the first camera was padded
    for m, n, c in zip(out.masks, out.nominal_masks, cams, strict=True):
        assert m.shape == n.shape == (2, c.height, c.width) and m.all() and not n.any()
    assert out.coeffs.shape == (2, 3, 4)
