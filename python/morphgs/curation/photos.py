"""Pairs at a capture's own photos (`curate --trajectory photos`): each pair is a run of `frames`
consecutive photos along the capture's camera sequence (video order, or a nearest-neighbour path
through the cameras when the photos have none: `trajectory.camera_sequence`), at the photos' own
cameras; the clean side is the photos themselves, the corrupted side the corrupted scene
rendered at those cameras. Clean frames are then real pixels, and a pair's residual holds both
the corruption and the scene's own error against the photo (docs/curation.md).

A pair has one size; a photo of another aspect (a 4:3 photo in a 16:9 pair, a portrait phone frame
in a landscape pair, a capture of both orientations) is scaled to cover it and centre-cropped, its
camera with it (`cover_crop`), so pixels stay square and the photo and its camera agree, as
`trajectory.resize_camera` treats a camera of the other orientation.
"""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = ["cover_crop", "photo_run"]

ASPECT_TOLERANCE = 0.02  # photos within 2 % of the pair's aspect are resized to it exactly


def cover_crop(img: np.ndarray, cam: Any, width: int, height: int) -> tuple[np.ndarray, Any]:
    """A photo (H, W, 3) and its camera at `width` x `height`: resized (Lanczos) to the smallest
    size of the photo's aspect that covers the target, then the centre cropped out; the camera is
    resized to that same integer size and its principal point moved by the crop's offset, so every
    world point lands on the same photo content as before."""
    from PIL import Image

    pw, ph = cam.width, cam.height
    s = max(width / pw, height / ph)
    rw, rh = max(width, round(pw * s)), max(height, round(ph * s))
    ox, oy = (rw - width) // 2, (rh - height) // 2
    big = np.asarray(Image.fromarray(img).resize((rw, rh), Image.Resampling.LANCZOS))
    c = cam.resized(rw, rh)
    out = type(cam)(c.fx, c.fy, c.cx - ox, c.cy - oy, width, height, c.world_to_camera, c.near, c.far)
    return np.ascontiguousarray(big[oy:oy + height, ox:ox + width]), out


def photo_run(source: Any, recorded: Any, index: int, frames: int, resolution: tuple[int, int],
              stride: int | None) -> tuple[Any, np.ndarray]:
    """(cameras, photos as uint8 (F, H, W, 3)) of pair `index` of a scene whose cameras have their
    photos: run `index` mod (number of runs), runs starting every `stride` (default `frames`)
    photos along the camera sequence; photos and cameras at `resolution` (W, H). `recorded`: the
    scene's recorded cameras (None: it has none).

    Photos within 2 % of the pair's aspect are resized to it; others are covered and
    centre-cropped (`cover_crop`).

    Raises:
        ValueError: a scene without photos, or fewer photos than `frames`.
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
        if abs((pw / ph) / (w / h) - 1) > ASPECT_TOLERANCE:
            im, cam = cover_crop(im, cam, w, h)
        elif (pw, ph) != (w, h):
            im = np.asarray(Image.fromarray(im).resize((w, h), Image.Resampling.LANCZOS))
            cam = cam.resized(w, h)
        out.append(im)
        cams[k] = cam
    return Cameras.from_list(cams), np.stack(out)
