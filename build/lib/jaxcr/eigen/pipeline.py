"""From a stereo dataset to descriptors: colour labelling (jitted batches), contours and
stereo angular histograms for every frame (Reiter et al. Fig. 3, steps 1-4).

Contours do not depend on the bin count, so they are extracted once
(:func:`dataset_contours`) and turned into histograms for any ``n_bins``
(:func:`stereo_histograms`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import jax.numpy as jnp
import numpy as np

from jaxcr.eigen.colour import ColourModel, label_batch
from jaxcr.eigen.descriptor import Contours, contour_histograms, mask_contours
from jaxcr.errors import InputError


@dataclass
class StereoContours:
    """Per camera (left, right) contours of the same frames ``ids``."""

    ids: list[str]
    views: tuple[Contours, Contours]
    #: frames left out because an image could not be read: {frame id: one-line reason}
    unreadable: dict[str, str] = field(default_factory=dict)

    @property
    def ok(self) -> np.ndarray:
        return self.views[0].ok & self.views[1].ok


def check_cameras(dataset, cameras: tuple[str, str]) -> None:
    for c in cameras:
        if c not in dataset.cameras:
            raise InputError(
                f"dataset has no camera {c!r} (cameras: {sorted(dataset.cameras)})",
                file=str(dataset.root),
                field="cameras",
            )


def label_images(colour: ColourModel, images: np.ndarray) -> np.ndarray:
    """Marker masks (B, H, W) of RGB images (B, H, W, 3) in [0, 1]."""
    return np.asarray(label_batch(colour, jnp.asarray(images, jnp.float32)))


def dataset_contours(
    dataset,
    colour: ColourModel,
    cameras: tuple[str, str] = ("left", "right"),
    spacing: float = 2.0,
    batch: int = 16,
    progress: bool = True,
    frames=None,
) -> StereoContours:
    """Contours of every frame (or the given ``frames``) of a loaded dataset, both views.

    A frame whose image cannot be read (missing, corrupt, wrong size) is left out and listed
    in ``unreadable`` with the one-line reason naming the file: one bad frame never fails the
    batch."""
    check_cameras(dataset, cameras)
    frames = list(dataset.frames if frames is None else frames)
    parts: dict[str, list[Contours]] = {c: [] for c in cameras}
    ids: list[str] = []
    unreadable: dict[str, str] = {}
    shapes: dict[str, tuple] = {}  # per camera, of the first frame read
    rng = range(0, len(frames), batch)
    if progress:
        from jaxcr.progress import progress as progress_bar

        rng = progress_bar(rng, desc=f"contours {dataset.name}", unit="batch", leave=False)
    for i in rng:
        imgs: dict[str, list[np.ndarray]] = {c: [] for c in cameras}
        for f in frames[i : i + batch]:
            try:
                views = {c: f.load_image(c) for c in cameras}
                for c, v in views.items():
                    first = shapes.setdefault(c, v.shape)
                    if v.shape != first:
                        raise InputError(
                            f"image is {v.shape[1]}x{v.shape[0]}, the dataset's first frame "
                            f"{first[1]}x{first[0]}",
                            file=str(f.images.get(c)),
                            frame=f.id,
                            field=f"images.{c}",
                        )
            except InputError as err:
                unreadable[f.id] = err.format()
                continue
            ids.append(f.id)
            for c in cameras:
                imgs[c].append(views[c])
        if not imgs[cameras[0]]:
            continue
        for cam in cameras:
            parts[cam].append(mask_contours(label_images(colour, np.stack(imgs[cam])), spacing))
    if not ids and unreadable:
        first = next(iter(unreadable.values()))
        raise InputError(f"no frame of the dataset could be read ({first})",
                         file=str(dataset.root))  # fmt: skip
    views = tuple(Contours.concat(parts[c]) for c in cameras)
    return StereoContours(ids, views, unreadable)  # type: ignore[arg-type]


def view_centres(sc: StereoContours) -> np.ndarray:
    """Fixed histogram reference points (2, 2): per view (left, right) the mean region
    centroid (x, y pixels) over the frames with markers in both views. Computed on the
    training set and stored in the model (see :mod:`jaxcr.eigen.descriptor`)."""
    ok = sc.ok
    if not ok.any():
        raise InputError("no frame has marker pixels in both views: no histogram centre")
    return np.stack([np.asarray(v.centres)[ok].mean(axis=0) for v in sc.views])


def stereo_histograms(
    sc: StereoContours,
    n_bins: int,
    normalise: bool = True,
    centres: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Stereo descriptors H~ = [H_L, H_R] (n, 2 n_bins) and ok (n,).

    ``centres``: None = per-frame region centroids (the paper); (2, 2) = a fixed reference
    point per view (:func:`view_centres`)."""
    if centres is not None and np.shape(centres) != (2, 2):
        raise InputError(f"view centres must be (2, 2) (x, y per view), got {np.shape(centres)}")
    cl, cr = (None, None) if centres is None else np.asarray(centres, np.float64)
    hl = contour_histograms(sc.views[0], n_bins, normalise, cl)
    hr = contour_histograms(sc.views[1], n_bins, normalise, cr)
    return np.concatenate([hl, hr], axis=1), sc.ok
