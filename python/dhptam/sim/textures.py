"""Photographs for the simulated room: scikit-image's bundled sample images.

They ship inside the scikit-image wheel (no download). Colour images are converted to grey
with OpenCV's luma weights; every photo is used at its own resolution (the renderer filters
it with mip-maps).
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from ..errors import DhptamError

# Real photographs (and photo-like scans) that scikit-image installs with the package.
PHOTO_NAMES = (
    "astronaut",
    "camera",
    "coffee",
    "chelsea",
    "rocket",
    "brick",
    "grass",
    "gravel",
    "moon",
    "coins",
)


def load_photos(names: tuple[str, ...] = PHOTO_NAMES) -> list[npt.NDArray[np.uint8]]:
    """The named ``skimage.data`` images as 2-D uint8 grey arrays.

    >>> photos = load_photos(("camera", "coffee"))
    >>> [p.shape for p in photos], photos[0].dtype
    ([(512, 512), (400, 600)], dtype('uint8'))
    """
    try:
        import skimage.data
    except ImportError as err:
        raise DhptamError(
            "the simulator's photographs come from scikit-image: pip install 'dhptam[sim]'"
        ) from err
    import cv2

    photos = []
    for name in names:
        image = np.asarray(getattr(skimage.data, name)())
        if image.ndim == 3:
            image = cv2.cvtColor(np.ascontiguousarray(image[..., :3]), cv2.COLOR_RGB2GRAY)
        photos.append(np.ascontiguousarray(image, dtype=np.uint8))
    return photos
