"""Pairs at a capture's own photos (`curate --trajectory photos`): each pair is a run of `frames`
consecutive photos along the capture's camera sequence (video order, or a nearest-neighbour path
through the cameras when the photos have none: `trajectory.camera_sequence`), at the photos' own
cameras; the clean side is the photos themselves, the corrupted side the corrupted scene
rendered at those cameras. Clean frames are then real pixels, and a pair's residual holds both
the corruption and the scene's own error against the photo (docs/curation.md).
"""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = ["photo_run"]

ASPECT_TOLERANCE = 0.02  # photos within 2 % of the pair's aspect are resized to it exactly


def photo_run(source: Any, recorded: Any, index: int, frames: int, resolution: tuple[int, int],
              stride: int | None) -> tuple[Any, np.ndarray]:
    """(cameras, photos as uint8 (F, H, W, 3)) of pair `index` of a scene whose cameras have their
    photos: run `index` mod (number of runs), runs starting every `stride` (default `frames`)
    photos along the camera sequence; photos and cameras at `resolution` (W, H). `recorded`: the
    scene's recorded cameras (None: it has none).

    Raises:
        ValueError: a scene without photos, fewer photos than `frames`, or photos of another
            aspect than `resolution` (naming the scene, both sizes and a size to use).
    """
    from PIL import Image

    from morphgs.camera import Cameras
    from morphgs.curation.sparse import _real_images
    from morphgs.trajectory import camera_sequence

    found = _real_images(source, len(recorded)) if recorded is not None else None
    if found is None:
        raise ValueError(f"scene {source.id}: trajectory 'photos' needs a scene folder whose cameras have their "
                         "photos (transforms.json or a COLMAP model with every image)")
    posed, order = found
    seq = camera_sequence(np.stack([posed.cameras[i].center for i in order]))
    if len(seq) < frames:
        raise ValueError(f"scene {source.id}: {len(seq)} photos, fewer than a pair's {frames} frames")
    step = stride or frames
    starts = list(range(0, len(seq) - frames + 1, step))
    run = [order[i] for i in seq[starts[index % len(starts)]:][:frames]]
    imgs, cams = posed.load(run)
    w, h = resolution
    out = []
    for k, (im, cam) in enumerate(zip(imgs, cams)):
        pw, ph = cam.width, cam.height
        if (pw, ph) != (w, h):
            if abs((pw / ph) / (w / h) - 1) > ASPECT_TOLERANCE:
                raise ValueError(f"scene {source.id}: photo {posed.paths[run[k]].name} is {pw}x{ph}, not of the pair "
                                 f"size {w}x{h}'s aspect: pass a resolution of the photos' aspect, e.g. "
                                 f"{w}x{max(1, round(w * ph / pw))}")
            im = np.asarray(Image.fromarray(im).resize((w, h), Image.Resampling.LANCZOS))
            cam = cam.resized(w, h)
        out.append(im)
        cams[k] = cam
    return Cameras.from_list(cams), np.stack(out)
