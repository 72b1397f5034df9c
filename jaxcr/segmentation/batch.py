"""The batch loop behind ``jaxcr segment``: frames in fixed-size chunks through nominal
kinematics, background subtraction and :func:`jaxcr.segmentation.refine.refine_batch` (or
:func:`~jaxcr.segmentation.refine.refine_sequence` for ``--warm-start``), then each frame's files and its
``results.jsonl`` record are written (files first, record last; see :mod:`jaxcr.io.results`).

Every chunk has exactly ``batch_size`` frames (the last one is padded by repeating a frame,
whose results are discarded), so the whole run compiles once.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from jaxcr._timing import CompileTimer
from jaxcr.errors import InputError
from jaxcr.io import exported
from jaxcr.io import results as R
from jaxcr.io.exported import FAST_COMPILE, cached_call
from jaxcr.io.overlay import fig4_panel
from jaxcr.kinematics.batch import forward_batch
from jaxcr.segmentation.buckets import bucket_shape, pad_frames

#: ``Segmenter(roi=)`` / ``jaxcr segment --roi``: tracked frames on a region of interest
#: never, always, or where it is expected to pay (large images; decisions S28)
ROI_MODES = ("auto", "on", "off")

FK_FAILED = "kinematics failed (solver did not converge or non-finite shape)"


def _background_fn(kind: str, ds, camera: str, colour_ranges=None) -> Callable:
    """A jitted batch function images (F, h, w, 3) -> (B (F, h, w), I' (F, h, w, 3));
    ``colour_ranges``: the colour mask's robot HSV boxes (None = its default)."""
    from jaxcr.segmentation import background as bgm

    if kind == "colour":
        ranges = bgm.ROBOT_HSV if colour_ranges is None else tuple(colour_ranges)
        return jax.jit(jax.vmap(lambda im: bgm.colour_mask(im, ranges=ranges)))
    if kind == "none":
        return jax.jit(jax.vmap(bgm.no_mask))
    if kind == "gmm":
        from jaxcr.io.images import read_image

        paths = ds.background_images.get(camera, [])
        if not paths:
            raise InputError(
                f"--background gmm needs robot-free background images for camera '{camera}' "
                "(dataset.json 'background_images')",
                file=str(ds.root),
                field="background_images",
            )
        stack = jnp.asarray(np.stack([read_image(p) for p in paths]))
        model = bgm.fit_background_model(stack, n_components=min(3, len(paths)))
        return jax.jit(jax.vmap(lambda im: bgm.background_model_mask(model, im)))
    raise InputError(f"unknown background subtraction {kind!r}", field="background")


def _plate_image(ds, camera: str) -> np.ndarray:
    """The first background image of ``camera`` (the plate of ``--background plate``)."""
    from jaxcr.io.images import read_image

    paths = ds.background_images.get(camera, [])
    if not paths:
        raise InputError(
            f"--background plate needs a background image (plate) for camera '{camera}' "
            "(dataset.json 'background_images')",
            file=str(ds.root),
            field="background_images",
        )
    return np.asarray(read_image(paths[0]))


def _entry_from_projection(uv, ok, width, height):
    """Entry pixel and direction for the plate foreground from the projected nominal
    centreline (n, 2): its first point inside the image, heading towards the point ~10 px
    further along. (None, None) if no point is inside (then the entry is searched at the
    image border)."""
    inside = ok & np.all(np.isfinite(uv), 1)
    inside &= (uv[:, 0] >= 0) & (uv[:, 0] <= width - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= height - 1)
    idx = np.flatnonzero(inside)
    if not len(idx):
        return None, None
    j = idx[0]
    seg = np.linalg.norm(np.diff(uv[j:], axis=0), axis=1)
    far = np.flatnonzero(np.cumsum(seg) >= 10.0)
    if not len(far):
        return uv[j], None
    return uv[j], uv[j + far[0] + 1] - uv[j]


def build_segmenter(dataset: str, cameras, config, background: str, out: str, **kwargs):
    """A :class:`Segmenter` from picklable arguments (dataset path, options): the
    :class:`jaxcr.scale.executor.WorkerSpec` of a Ray worker, which loads the dataset itself."""
    from jaxcr.io.dataset import load_dataset

    return Segmenter(load_dataset(Path(dataset)), cameras, config, background, out, **kwargs)


def _trace_record(tr) -> dict:
    """The ``foreground`` entry of a results record for one camera (pixels, OpenCV
    convention)."""
    return {
        "tip_px": [float(x) for x in tr.tip],
        "entry_px": [float(x) for x in tr.entry],
        "backbone_px": np.round(np.asarray(tr.backbone, float), 2).tolist(),
        "gaps": [list(map(int, g)) for g in tr.gaps],
        "plate_shift_px": [float(x) for x in tr.shift],
        "width_px": float(tr.width_px),
        "reason": tr.reason,
    }


class Segmenter:
    """Runs the segmentation of selected frames of a dataset into an output folder.

    Attributes:
        frame_ids: every frame id of the dataset (bad frames first, then usable frames in
            file order).
        compile_s, run_s: accumulated compile and execution seconds of this process.
    """

    def __init__(
        self,
        ds,
        cameras: list[str],
        config,
        background: str,
        out: str | Path,
        overlays: bool = True,
        warm_start: bool = False,
        batch_size: int = 4,
        colour_ranges=None,
        plate_config=None,
        log_dir: str | Path | None = None,
        uncertainty: bool = True,
        depth_factor: float | None = None,
        warn: Callable[[str], None] | None = None,
        roi: str = "off",
        shape_buckets: bool = False,
    ):
        if ds.robot is None:
            raise InputError(
                f"robot kind {ds.robot_dict.get('kind')!r} is not supported by this build",
                file=str(ds.root),
                field="robot",
            )
        self.ds = ds
        self.cams = list(cameras)
        self.config = config
        self.layout = R.OutputLayout(out, log_dir=log_dir)
        self.overlays = overlays
        self.warm_start = warm_start
        if roi not in ROI_MODES:
            raise InputError(f"roi must be one of {', '.join(ROI_MODES)}, got {roi!r}", field="roi")
        self.roi = roi
        # images padded to the ladder's bucket (jaxcr.segmentation.buckets, decisions S29): the
        # image-size-dependent programs are compiled per bucket, not per size
        self.shape_buckets = bool(shape_buckets)
        self._roi_run = None  # the region of interest of the run so far ("auto")
        self.batch_size = int(batch_size)
        self.frames = {f.id: f for f in ds.frames}
        self.frame_ids = list(ds.bad_frames) + [f.id for f in ds.frames]
        self.cameras = tuple(ds.cameras[c] for c in self.cams)
        self.plate_config = plate_config
        # the Laplace tip covariance (jaxcr.segmentation.uncertainty), once per frame after
        # convergence; ``warn`` is called once per run, at the first depth-ambiguous frame
        from jaxcr.segmentation.uncertainty import DEPTH_FACTOR

        self.uncertainty = bool(uncertainty)
        self.depth_factor = DEPTH_FACTOR if depth_factor is None else float(depth_factor)
        self.warn = warn
        self.depth_ambiguous: list[str] = []  # frame ids flagged in this process
        self.uncertainty_s = 0.0
        # the per-pixel GMM's model has the real image's shape: its mask is computed at the
        # real size and padded (the colour and no-mask functions run on the padded arrays)
        self._bg_real_size = background == "gmm"
        if background == "plate":
            self.plates = {c: _plate_image(ds, c) for c in self.cams}
            self.bg_fns = {}
        else:
            self.bg_fns = {c: _background_fn(background, ds, c, colour_ranges) for c in self.cams}
        self.compile_s = 0.0
        self.run_s = 0.0
        self._coeffs_prev = None  # warm start carried across chunks
        self._cam_prev = None  # and the camera-pose correction with it
        self._hess_prev = None  # and the solver's inverse Hessian
        self._started = False  # the first chunk's programs were queued (_compile_ahead)

    def _roi_arg(self, bases) -> tuple[int, int] | str | None:
        """``refine_sequence``'s ``roi`` for this chunk's tracked frames (``self.roi``:
        "off"; "on" = a region sized per chunk by
        :func:`~jaxcr.segmentation.refine.tracking_roi`; "auto" = that region where
        :func:`~jaxcr.segmentation.refine.roi_pays`, grown to the largest one of the run so
        that later chunks reuse its compiled program; decisions S28). ``bases``: the chunk's
        nominal centrelines."""
        from jaxcr.segmentation.refine import roi_pays, tracking_roi

        if self.roi == "on":
            return "auto"
        if self.roi == "off" or not roi_pays(self.cameras, (0, 0)):
            return None  # (0, 0): the image-size condition alone; small images skip the boxes
        roi = tracking_roi(bases, self.cameras, config=self.config.warm())
        if roi is not None and self._roi_run is not None:
            roi = (max(roi[0], self._roi_run[0]), max(roi[1], self._roi_run[1]))
        if not roi_pays(self.cameras, roi):
            return None
        self._roi_run = roi
        return roi

    # ------------------------------------------------------------------ per-frame checks

    def _check_frame(self, fid: str):
        """(images per camera, None) for a usable frame, or (None, reason)."""
        if fid in self.ds.bad_frames:
            return None, f"bad frame: {self.ds.bad_frames[fid]}"
        f = self.frames[fid]
        q = np.asarray(f.q, np.float64)
        if q.shape != (self.ds.robot.n_joints,):
            return None, f"q has {q.size} values, the robot has {self.ds.robot.n_joints} joints"
        if not np.all(np.isfinite(q)):
            return None, "non-finite joint values (NaN or inf in q)"
        if np.any(np.abs(q) > np.finfo(np.float32).max):
            return None, "joint values beyond the float32 range (|q| > 3.4e38)"
        images = []
        for cname, cam in zip(self.cams, self.cameras, strict=True):
            try:
                im = f.load_image(cname)
            except InputError as err:
                return None, f"image missing or unreadable: {err}"
            if im.shape[:2] != (cam.height, cam.width):
                return None, (
                    f"image of camera '{cname}' is {im.shape[1]}x{im.shape[0]}, "
                    f"the camera is {cam.width}x{cam.height}"
                )
            if not np.all(np.isfinite(im)):
                return None, f"image of camera '{cname}' has non-finite values"
            images.append(im)
        return images, None

    def _failed_record(self, fid: str, reason: str) -> dict:
        f = self.frames.get(fid)
        return {
            "format": R.RESULTS_FORMAT,
            "frame": fid,
            "ok": False,
            "reason": reason,
            "tags": list(f.tags) if f is not None else [],
            "cameras": self.cams,
        }

    # ------------------------------------------------------------------ the loop

    def process(self, frame_ids: list[str]) -> Iterator[dict]:
        """Yield one record per frame of ``frame_ids``, in that order, each as soon as its
        files are written (atomically) and every earlier frame's record has been yielded:
        failed records for frames that cannot be processed, the others from compiled chunks
        of ``batch_size``. Writes no results log: the caller appends each record as it comes
        (:func:`jaxcr.scale.executor.run_frames`, which also runs this on Ray workers), so an
        interrupted run keeps every frame finished before the interruption."""
        ready: dict[str, dict] = {}
        order = iter(frame_ids)
        waiting = next(order, None)

        def flush():
            nonlocal waiting
            while waiting is not None and waiting in ready:
                yield ready.pop(waiting)
                waiting = next(order, None)

        pending: list[tuple[str, list[np.ndarray]]] = []
        for fid in frame_ids:
            images, reason = self._check_frame(fid)
            if reason is not None:
                ready[fid] = self._failed_record(fid, reason)
                yield from flush()
                continue
            pending.append((fid, images))
            if len(pending) == self.batch_size:
                for rec in self._process_chunk(pending):
                    ready[rec["frame"]] = rec
                    yield from flush()
                pending = []
        if pending:
            for rec in self._process_chunk(pending):
                ready[rec["frame"]] = rec
                yield from flush()

    def failed_record(self, fid: str, reason: str) -> dict:
        return self._failed_record(fid, reason)

    def run(self, frame_ids: list[str], progress: bool = True, executor=None, spec=None):
        """Process ``frame_ids``, appending one record per frame to ``results.jsonl`` as
        chunks complete; returns the :class:`jaxcr.scale.executor.RunStats` (records in
        order). ``executor``: a :class:`jaxcr.scale.executor.ExecutorConfig` (default: local,
        chunks of ``batch_size``); ``spec``: the :class:`~jaxcr.scale.executor.WorkerSpec`
        that builds this Segmenter in a Ray worker (required for ``ray``)."""
        from jaxcr.progress import progress as progress_bar
        from jaxcr.scale.executor import ExecutorConfig, run_frames

        executor = executor or ExecutorConfig()
        if executor.kind != "local" and spec is None:
            raise InputError("a Ray run needs the worker's spec", field="executor")
        bar = progress_bar(
            total=len(frame_ids),
            unit="frame",
            enabled=progress,
            desc="segment",
            # always frames/s (tqdm would switch to s/frame below 1 frame/s)
            bar_format="{l_bar}{bar}| {n_fmt}/{total_fmt} [{elapsed}<{remaining}, "
            "{rate_noinv_fmt}]",
        )
        with R.ResultsLog(self.layout.results) as log:
            stats = run_frames(
                spec, frame_ids, log, executor, chunk=self.batch_size, local_worker=self,
                on_record=lambda rec: bar.update(1),
            )  # fmt: skip
        bar.close()
        if executor.kind != "local":  # the workers' compile and run time
            self.compile_s += stats.compile_s
            self.run_s += stats.run_s
            if self.layout.log_root == self.layout.root:
                # a worker killed mid-write leaves its temporary file; every worker is done and
                # this (unsharded) run holds OUT's lock, so none is being written
                from jaxcr.io.outdir import clean_leftovers

                clean_leftovers(self.layout.root)
        return stats

    def _compile_ahead(self, chunk) -> float:
        """Before the first chunk: a dry run of it inside :func:`jaxcr.io.exported.compile_ahead`,
        which queues the kinematics, the refinement and the covariance for XLA side by side
        (each program's stored trace is loaded or traced and lowered here, one after the other;
        XLA then compiles them in two threads) instead of one after the other as the real chunk
        reaches each. The dry run's values (zeros) are discarded; no file is written, no
        result or timer kept: its wall seconds (tracing, lowering, waiting for XLA) are returned
        and counted as the first chunk's compile time. Only with the compilation cache on
        (else cached_call would run the programs)."""
        self._started = True
        if not exported.programs_stored():
            return 0.0
        t0 = time.perf_counter()
        keep = (self.compile_s, self.run_s, self.uncertainty_s, list(self.depth_ambiguous),
                self._coeffs_prev, self._cam_prev, self._hess_prev, self.warn)  # fmt: skip
        self.warn = None
        try:
            with exported.compile_ahead():
                for _ in self._process_chunk(chunk, dry=True):
                    pass
        except Exception:  # the real chunk will compile, and report, whatever failed here
            pass
        finally:
            (self.compile_s, self.run_s, self.uncertainty_s, self.depth_ambiguous,
             self._coeffs_prev, self._cam_prev, self._hess_prev, self.warn) = keep  # fmt: skip
        return time.perf_counter() - t0

    def _process_chunk(self, chunk: list[tuple[str, list[np.ndarray]]], dry: bool = False):
        from jaxcr.segmentation.refine import FAILURES, refine_batch, refine_sequence

        ahead_s = 0.0 if self._started else self._compile_ahead(chunk)
        n = len(chunk)
        # pad at the end (results discarded): one compiled shape for the whole run
        full = chunk + [chunk[-1]] * (self.batch_size - n)
        B = len(full)
        qs = jnp.asarray(np.stack([self.frames[fid].q for fid, _ in full]), jnp.float32)
        imgs_np = [np.stack([ims[k] for _, ims in full]) for k in range(len(self.cams))]
        # the arrays the compiled programs see: padded to each camera's bucket (S29)
        shapes = [self._array_shape(cam) for cam in self.cameras]
        imgs_in = [pad_frames(im, sh) for im, sh in zip(imgs_np, shapes, strict=True)]
        with CompileTimer() as timer:
            # through the stored traced program too, as the refinement: a second process then
            # neither traces nor lowers the kinematics (a CTR's shooting solver is the largest
            # of them). Compiled for a short compile (XLA's legacy loop emitter, FAST_COMPILE):
            # it runs once per chunk, a few ms, and its outputs are bit-identical
            # (docs/decisions.md S22; the covariance's run time doubled with it: not used there).
            # The same function and options as the synthetic-data generator's kinematics, so
            # `jaxcr demo` (synth then segment, B = frames = batch size) has one CTR program
            # (docs/decisions.md S25)
            fk = cached_call(forward_batch, self.ds.robot, qs, compiler_options=FAST_COMPILE)
            bgs, subs = [], []
            traces = None
            if not self.bg_fns and dry:  # the dry run needs the shapes, not fk's plate traces
                bgs = [jnp.asarray(np.zeros(im.shape[:3], bool)) for im in imgs_in]
                subs = [jnp.asarray(im.astype(np.float32)) for im in imgs_in]
                traces = []
            elif not self.bg_fns:  # --background plate: per frame, from the nominal base
                bgs, subs, traces = self._plate_backgrounds(fk, imgs_np)
                # padded as background (the refinement weighs the padding zero either way)
                bgs = [jnp.asarray(pad_frames(np.asarray(b), sh, fill=True))
                       for b, sh in zip(bgs, shapes, strict=True)]  # fmt: skip
                subs = [jnp.asarray(pad_frames(np.asarray(x), sh))
                        for x, sh in zip(subs, shapes, strict=True)]  # fmt: skip
            for k, cname in enumerate(self.cams):
                if traces is not None:
                    break
                # per-pixel masks: the padding does not change a real pixel's
                if self._bg_real_size:
                    bg, sub = self.bg_fns[cname](jnp.asarray(imgs_np[k]))
                    bg = jnp.asarray(pad_frames(np.asarray(bg), shapes[k], fill=True))
                    sub = jnp.asarray(pad_frames(np.asarray(sub), shapes[k]))
                else:
                    bg, sub = self.bg_fns[cname](jnp.asarray(imgs_in[k]))
                bgs.append(bg)
                subs.append(sub)
            valid = jnp.asarray(fk.ok, bool)
            if self.warm_start:
                res = refine_sequence(
                    fk.centreline,
                    self.cameras,
                    tuple(subs),
                    tuple(bgs),
                    self.config,
                    init=self._coeffs_prev,
                    init_cam=self._cam_prev,
                    init_hessian=self._hess_prev,
                    valid=valid,
                    jit_call=cached_call,
                    roi=self._roi_arg(fk.centreline),
                    shape_buckets=self.shape_buckets,
                )
            else:
                res = refine_batch(
                    fk.centreline,
                    self.cameras,
                    tuple(subs),
                    tuple(bgs),
                    self.config,
                    valid=valid,
                    jit_call=cached_call,
                    shape_buckets=self.shape_buckets,
                )
            res = jax.block_until_ready(res)
        self.compile_s += timer.compile_s + ahead_s
        self.run_s += timer.run_s
        per_frame = timer.run_s / B
        compile_share = (timer.compile_s + ahead_s) / max(n, 1)
        unc, unc_per_frame = None, 0.0
        if self.uncertainty:
            from jaxcr.segmentation.uncertainty import shape_uncertainty_batch

            with CompileTimer() as utimer:
                unc = shape_uncertainty_batch(
                    fk.centreline,
                    self.cameras,
                    tuple(subs),
                    tuple(bgs),
                    self.config,
                    res.coeffs,
                    res.camera_correction,
                    jit_call=cached_call,
                    shape_buckets=self.shape_buckets,
                )
                unc = jax.tree.map(np.asarray, jax.block_until_ready(unc))
            self.compile_s += utimer.compile_s
            self.run_s += utimer.run_s
            self.uncertainty_s += utimer.run_s
            unc_per_frame = utimer.run_s / B
            compile_share += utimer.compile_s / max(n, 1)

        host = jax.tree.map(np.asarray, res)
        if self.shape_buckets:  # the outputs at the real image size (never the padding)
            crop = [(c.height, c.width) for c in self.cameras]
            host = dataclasses.replace(
                host,
                masks=tuple(m[:, :h, :w] for m, (h, w) in zip(host.masks, crop, strict=True)),
                nominal_masks=tuple(
                    m[:, :h, :w] for m, (h, w) in zip(host.nominal_masks, crop, strict=True)
                ),
            )
        fk_ok = np.asarray(fk.ok)
        fk_res = np.asarray(fk.residual)
        fk_steps = np.asarray(fk.num_steps)
        bgs_np = [
            np.asarray(b)[:, : c.height, : c.width] for b, c in zip(bgs, self.cameras, strict=True)
        ]
        nominal_p = np.asarray(fk.centreline.p)
        if self.warm_start:
            ok_idx = [i for i in range(n) if bool(host.ok[i])]
            if ok_idx:
                self._coeffs_prev = jnp.asarray(host.coeffs[ok_idx[-1]])
                self._cam_prev = jnp.asarray(host.camera_correction[ok_idx[-1]])
                self._hess_prev = jnp.asarray(host.hessian_inv[ok_idx[-1]])

        for i, (fid, images) in enumerate(chunk):
            frame = self.frames[fid]
            ok = bool(host.ok[i]) and bool(fk_ok[i])
            if not bool(fk_ok[i]):
                reason = FK_FAILED
            elif not ok:
                reason = FAILURES.get(int(host.failure[i]), f"failure {int(host.failure[i])}")
            else:
                reason = None
            rec = {
                "format": R.RESULTS_FORMAT,
                "frame": fid,
                "ok": ok,
                "reason": reason,
                "tags": list(frame.tags),
                "cameras": self.cams,
                "status": int(host.status[i]),
                "failure": int(host.failure[i]),
                "num_steps": int(host.num_steps[i]),
                "steps_per_level": host.steps_per_level[i].tolist(),
                "time_s": per_frame,
                "compile_s": compile_share,
                "band_exact": bool(host.band_exact[i]),
                "energy": {
                    f.name: float(getattr(host.energy, f.name)[i])
                    for f in dataclasses.fields(host.energy)
                },
                "coeffs": host.coeffs[i].tolist(),
                "fk": {
                    "ok": bool(fk_ok[i]),
                    "residual": float(fk_res[i]),
                    "num_steps": int(fk_steps[i]),
                },
            }
            if traces:
                rec["foreground"] = {
                    c: _trace_record(traces[k][i]) for k, c in enumerate(self.cams)
                }
            cc = getattr(host, "camera_correction", None)
            if cc is not None:  # per-camera pose correction (rotation vector, translation)
                rec["camera_correction"] = {c: cc[i][k].tolist() for k, c in enumerate(self.cams)}
            if ok and unc is not None:
                rec["uncertainty"] = self._uncertainty_record(fid, unc, i, unc_per_frame)
            if ok and not dry and np.all(np.isfinite(host.centreline.p[i])):
                rec["files"] = self._write_frame_files(
                    fid, frame, images, host, i, bgs_np, nominal_p[i]
                )
            yield rec

    def _array_shape(self, cam) -> tuple[int, int]:
        """(H, W) of the arrays camera ``cam``'s frames are compiled for: its bucket with
        shape buckets (:func:`jaxcr.segmentation.buckets.bucket_shape`), else its size."""
        if self.shape_buckets:
            return bucket_shape(cam.height, cam.width)
        return cam.height, cam.width

    def _uncertainty_record(self, fid: str, unc, i: int, time_s: float) -> dict:
        """The ``uncertainty`` entry of a results record (docs/uncertainty.md): per camera
        the 1-sigma tip uncertainty along the optical axis and in the image plane; ``None``
        (JSON null) for a sigma the images do not bound."""

        def fin(x, scale=1.0):
            x = float(x)
            return x * scale if np.isfinite(x) else None

        cams = {}
        flagged = None
        for k, c in enumerate(self.cams):
            d, lat = float(unc.sigma_depth[i][k]), float(unc.sigma_lateral[i][k])
            amb = bool(np.isinf(d) or d > self.depth_factor * lat)
            cams[c] = {
                "sigma_depth_mm": fin(d, 1e3),
                "sigma_image_mm": fin(lat, 1e3),
                "sigma_image_px": fin(unc.sigma_px[i][k]),
                "depth_ratio": fin(unc.depth_ratio[i][k]),
                "depth_ambiguous": amb,
                "noise_std": fin(unc.noise_std[i][k]),
            }
            if amb and flagged is None:
                flagged = (c, d, lat)
        if flagged is not None:
            if not self.depth_ambiguous and self.warn is not None:
                c, d, lat = flagged
                dtxt = "unbounded" if np.isinf(d) else f"{1e3 * d:.2g} mm"
                ltxt = "unbounded" if np.isinf(lat) else f"{1e3 * lat:.2g} mm"
                self.warn(
                    f"frame {fid}: the tip's 1-sigma uncertainty along camera '{c}''s optical "
                    f"axis ({dtxt}) exceeds {self.depth_factor:g} x the image-plane one "
                    f"({ltxt}): the images do not determine the depth (flag "
                    "'depth_ambiguous' in results.jsonl; docs/uncertainty.md); further such "
                    "frames are flagged without a message"
                )
            self.depth_ambiguous.append(fid)
        return {
            "model": "laplace-gauss-newton/1",
            "depth_factor": self.depth_factor,
            "depth_ambiguous": flagged is not None,
            "null_dims": int(unc.null_dims[i]),
            "tip_m": [float(x) for x in unc.tip[i]],
            "tip_cov_m2": np.asarray(unc.tip_cov[i], float).tolist(),
            "cameras": cams,
            "time_s": time_s,
        }

    def _plate_backgrounds(self, fk, imgs_np):
        """Plate foreground of every frame and camera (:func:`jaxcr.segmentation.foreground.
        plate_foreground`), entered where the projected nominal centreline enters the image
        and heading along it (:func:`_entry_from_projection`). Returns (B per camera (F, h, w), I' per
        camera, traces[camera][frame])."""
        from jaxcr.camera import project_points
        from jaxcr.segmentation.foreground import plate_foreground

        p_all = np.asarray(fk.centreline.p)
        bgs, subs, traces = [], [], []
        for k, cname in enumerate(self.cams):
            cam = self.cameras[k]
            uv_all, ok_all = jax.vmap(lambda p, c=cam: project_points(c, p))(
                jnp.asarray(p_all, jnp.float32)
            )
            uv_all, ok_all = np.asarray(uv_all, np.float64), np.asarray(ok_all)
            bk, tk = [], []
            for i in range(len(p_all)):
                entry, d = _entry_from_projection(uv_all[i], ok_all[i], cam.width, cam.height)
                tr = plate_foreground(
                    imgs_np[k][i], self.plates[cname], entry, d, self.plate_config
                )
                # The re-trace state (the reduced frame and plate) is for the two-view
                # branch choice of the stereo pipeline; a batch keeps every frame's trace.
                tr.retrace = None
                bk.append(~tr.mask)
                tk.append(tr)
            bg = np.stack(bk)
            im = imgs_np[k].astype(np.float32)
            bgs.append(jnp.asarray(bg))
            subs.append(jnp.asarray(im * (~bg)[..., None].astype(np.float32)))
            traces.append(tk)
        return bgs, subs, traces

    def _write_frame_files(self, fid, frame, images, host, i, bgs_np, nominal_p) -> dict:
        L = self.layout
        files: dict = {"masks": {}, "nominal": {}, "background": {}}
        if self.overlays:
            files["overlays"] = {}
        for k, cname in enumerate(self.cams):
            refined = host.masks[k][i]
            nominal = host.nominal_masks[k][i]
            fg = ~bgs_np[k][i]
            for key, arr in (("masks", refined), ("nominal", nominal), ("background", fg)):
                rel = getattr(L, {"masks": "mask"}.get(key, key))(cname, fid)
                R.atomic_write_png(L.abs(rel), arr)
                files[key][cname] = rel
            if self.overlays:
                truth = frame.load_mask(cname) if cname in frame.masks else None
                panel = fig4_panel(images[k], fg, nominal, refined, truth)
                rel = L.overlay(cname, fid)
                R.atomic_write_png(L.abs(rel), panel)
                files["overlays"][cname] = rel
        rel = L.centreline(fid)
        R.atomic_write_npy(L.abs(rel), host.centreline.p[i])
        files["centreline"] = rel
        rel = L.centreline_nominal(fid)
        R.atomic_write_npy(L.abs(rel), nominal_p)
        files["centreline_nominal"] = rel
        return files
