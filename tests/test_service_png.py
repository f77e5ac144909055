"""The render endpoint's PNG encoder: lossless through two independent decoders, any size."""

import io

import cv2
import numpy as np
import pytest
from PIL import Image

from service.png import encode_png


def images():
    gen = np.random.default_rng(0)
    yield gen.integers(0, 256, (37, 53, 3), dtype=np.uint8)  # noise: every filter byte wraps
    flat = np.full((64, 48, 3), 255, np.uint8)
    flat[20:40, 10:30] = (200, 30, 60)  # a render's look: background and a figure
    yield flat
    yield np.zeros((1, 1, 3), np.uint8)
    yield gen.integers(0, 256, (1, 7, 3), dtype=np.uint8)
    yield gen.integers(0, 256, (9, 1, 3), dtype=np.uint8)
    yield gen.integers(0, 256, (16, 32, 4), dtype=np.uint8)[..., :3]  # a non-contiguous view


@pytest.mark.parametrize("image", list(images()), ids=lambda a: "x".join(map(str, a.shape)))
def test_png_decodes_to_the_same_pixels(image):
    data = encode_png(image)
    with Image.open(io.BytesIO(data)) as png:
        png.load()
        assert png.format == "PNG" and png.mode == "RGB" and png.size == (image.shape[1], image.shape[0])
        assert np.array_equal(np.asarray(png), image)
    bgr = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    assert np.array_equal(bgr[..., ::-1].reshape(image.shape), image)


def test_flat_images_compress():
    assert len(encode_png(np.full((256, 256, 3), 255, np.uint8))) < 2_000  # raw: 196 KB


@pytest.mark.parametrize(
    "bad",
    [
        np.zeros((4, 4), np.uint8),
        np.zeros((4, 4, 4), np.uint8),
        np.zeros((4, 4, 3)),
        np.zeros((0, 4, 3), np.uint8),
    ],
)
def test_anything_but_rgb_bytes_is_refused(bad):
    with pytest.raises(ValueError, match=r"\[H, W, 3\] uint8"):
        encode_png(bad)
