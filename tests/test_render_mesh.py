"""The ground-truth mesh renderer: geometry lands where the OpenCV camera model says, depth and
triangle ids are exact, coverage is anti-aliased only at edges, the z-buffer keeps the nearest."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from eva_engine.geometry import vertex_normals
from eva_engine.render.camera import intrinsics, look_at
from eva_engine.render.mesh import MeshRenderConfig, MeshRenderer

QUAD = np.array([[0, 1, 2], [0, 2, 3]])


def quad(x0, y0, x1, y1, z):
    return np.array([[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]], np.float32)


@pytest.fixture(scope="module")
def renderer():
    faces = np.concatenate([QUAD, QUAD + 4])
    with MeshRenderer(
        faces, MeshRenderConfig(width=40, height=30, supersample=4, background=(0.0, 0.0, 1.0))
    ) as r:
        yield r


def test_projection_depth_and_ids(renderer):
    K = torch.tensor([[20.0, 0.0, 20.0], [0.0, 20.0, 15.0], [0.0, 0.0, 1.0]])
    # Front quad covers camera x in [-0.2, 0.2], y in [-0.1, 0.3] at z = 2 -> pixels x 18..22, y 14..18.
    verts = np.concatenate([quad(-0.2, -0.1, 0.2, 0.3, 2.0), quad(-1.0, -1.0, 1.0, 1.0, 3.0)])
    renderer.set_surface(colors=np.array([[1, 0, 0]] * 4 + [[0, 1, 0]] * 4, np.float32))
    out = renderer.render(verts, torch.eye(4), K)
    assert out.rgb.shape == (30, 40, 3) and out.alpha.shape == (30, 40)
    front = (out.face_id >= 0) & (out.face_id <= 1)
    ys, xs = np.nonzero(front.numpy())
    assert (xs.min(), xs.max(), ys.min(), ys.max()) == (18, 21, 14, 17)
    assert torch.allclose(out.depth[front], torch.tensor(2.0), atol=1e-5)
    assert torch.allclose(out.depth[out.face_id >= 2], torch.tensor(3.0), atol=1e-5)
    # Back quad spans camera x,y in [-1, 1] at z = 3: pixels x 13.33..26.67, y 8.33..21.67.
    assert out.alpha[15, 14] == 1.0 and out.alpha[15, 12] == 0.0
    assert 0.0 < out.alpha[15, 13] < 1.0  # a partly covered edge pixel
    assert torch.equal(
        out.rgb[out.alpha == 0], torch.tensor([[0.0, 0.0, 1.0]]).expand(int((out.alpha == 0).sum()), 3)
    )
    # The nearer red quad wins the z-buffer; the green one shows around it.
    assert out.rgb[16, 20, 0] > 0.3 and out.rgb[16, 20, 1] == 0.0
    assert out.rgb[10, 15, 1] > 0.3 and out.rgb[10, 15, 0] == 0.0
    labels = torch.tensor([5, 5, 7, 7])
    cover = out.label_coverage(labels, 5)
    assert float(cover.sum()) == pytest.approx(16.0, abs=1e-4)  # the 4x4-pixel front quad
    assert torch.all(cover <= out.alpha + 1e-6)


def test_pixels_are_the_float64_mean_of_their_samples_to_the_bit(renderer):
    """The box filter (summed slice by slice, uncovered samples as the background) gives what
    the plain float64 mean over each pixel's samples gives, bit for bit."""
    c, s = renderer.config, renderer.config.supersample
    rng = np.random.default_rng(0)
    color = rng.random((c.height * s, c.width * s, 3), dtype=np.float32) * 1.5
    ids = rng.integers(-1, 3, (c.height * s, c.width * s))
    ids[: 2 * s] = -1  # two rows of pixels with no sample covered
    color[ids < 0] = 0.0  # the clear colour of uncovered samples
    out = renderer._resolve(color, ids, rng.random(ids.shape, dtype=np.float32))
    bg = np.asarray(c.background, np.float32)
    covered = ids >= 0
    filled = np.where(covered[..., None], color, bg).reshape(c.height, s, c.width, s, 3)
    alpha = covered.reshape(c.height, s, c.width, s).mean(axis=(1, 3), dtype=np.float64).astype(np.float32)
    rgb = filled.mean(axis=(1, 3), dtype=np.float64).astype(np.float32)
    rgb = np.where(alpha[..., None] > 0, np.clip(rgb, 0.0, 1.0), bg)
    assert np.array_equal(out.alpha.numpy(), alpha) and np.array_equal(out.rgb.numpy(), rgb)
    assert alpha[:2].max() == 0.0 and 0.0 < alpha[2:].min() < 1.0 and alpha.max() == 1.0


def test_look_at_and_intrinsics():
    view = look_at((0.0, 1.0, 3.0), (0.0, 1.0, 0.0)).double()
    p = view[:3, :3] @ torch.tensor([0.1, 1.0, 0.0]).double() + view[:3, 3]
    assert torch.allclose(p, torch.tensor([0.1, 0.0, 3.0]).double(), atol=1e-9)  # world +X -> image right
    up = view[:3, :3] @ torch.tensor([0.0, 1.0, 0.0]).double()
    assert up[1] < 0  # world up is image up (camera y points down)
    K = intrinsics(64, 48, 90.0)
    assert K[1, 1] == pytest.approx(24.0) and K[0, 2] == 32.0


def test_bad_inputs_and_degenerate_normals(renderer):
    with pytest.raises(ValueError, match="NaN"):
        renderer.render(np.full((8, 3), np.nan, np.float32), torch.eye(4), torch.eye(3))
    with pytest.raises(ValueError, match=r"\[8, 3\]"):
        renderer.render(np.zeros((7, 3), np.float32), torch.eye(4), torch.eye(3))
    n = vertex_normals(np.zeros((4, 3)), QUAD)  # zero-area triangles
    assert np.isfinite(n).all() and np.allclose(np.linalg.norm(n, axis=1), 1.0)


def test_missing_egl_gives_a_clear_error(monkeypatch):
    import moderngl

    from eva_engine.render.mesh import MeshRenderError

    def no_egl(**kwargs):
        raise Exception("libEGL.so: cannot open shared object file")

    monkeypatch.setattr(moderngl, "create_standalone_context", no_egl)
    with pytest.raises(MeshRenderError, match="libegl1 libgl1 libegl-mesa0 libgl1-mesa-dri"):
        MeshRenderer(QUAD)
