"""The demo scene: body model + rasterizer end to end, and the surfel helpers it is built from."""

import numpy as np
import pytest
import torch

from eva_engine.demo import PART_COLORS, render_demo, surface_gaussians
from eva_engine.geometry import quat_from_z, vertex_normals
from eva_engine.render import quat_to_rotmat


def test_quat_from_z_maps_z_onto_direction():
    gen = torch.Generator().manual_seed(0)
    dirs = torch.nn.functional.normalize(torch.randn(64, 3, generator=gen), dim=-1)
    dirs = torch.cat([dirs, torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]])])
    rot = quat_to_rotmat(quat_from_z(dirs))
    assert torch.allclose(rot[:, :, 2], dirs, atol=1e-5)


def test_surfels_on_a_cube_point_outward():
    verts = torch.tensor([[x, y, z] for x in (-1.0, 1.0) for y in (-1.0, 1.0) for z in (-1.0, 1.0)])
    faces = torch.tensor(
        [
            [0, 1, 3],
            [0, 3, 2],
            [4, 6, 7],
            [4, 7, 5],
            [0, 4, 5],
            [0, 5, 1],
            [2, 3, 7],
            [2, 7, 6],
            [0, 2, 6],
            [0, 6, 4],
            [1, 5, 7],
            [1, 7, 3],
        ]
    )
    normals = torch.from_numpy(vertex_normals(verts, faces))
    assert (torch.sum(normals * verts, dim=-1) > 0).all()  # outward on a closed, consistently wound mesh
    g = surface_gaussians(verts, faces)
    # Longest edge at every corner is a face diagonal (2 sqrt 2).
    assert torch.allclose(g.scales[:, 0], torch.full((8,), 0.4 * 2 * 2**0.5))


def test_render_demo_shows_the_body_with_its_parts(anny_model):
    image = render_demo(anny_model, width=96, height=128, yaws=(0.0,))
    assert image.shape == (128, 96, 3) and torch.isfinite(image).all()
    covered = (image - 1.0).abs().amax(-1) > 0.05
    assert 0.1 < covered.float().mean() < 0.6  # a person, not an empty or flooded frame
    # Both the body colour and the hand colour appear (up to shading: compare hue ratios).
    flat = image[covered]
    chroma = flat / flat.sum(-1, keepdim=True)
    for colour in (PART_COLORS[0], PART_COLORS[1]):
        ref = torch.tensor(colour) / sum(colour)
        assert ((chroma - ref).abs().amax(-1) < 0.03).any()


@pytest.mark.slow
def test_eva_demo_runs_the_product_end_to_end(tmp_path):
    """The README's main command, shortened: video -> eva serve + eva worker -> renders via the API."""
    from PIL import Image
    from typer.testing import CliRunner

    from service.cli import app

    out, work, mp4 = tmp_path / "demo.png", tmp_path / "work", tmp_path / "demo.mp4"
    args = [
        "demo",
        "--out",
        str(out),
        "--workdir",
        str(work),
        "--preset",
        "tiny",
        "--iterations",
        "3",
        "--animation",
        str(mp4),
        "--fit-scale",
        "0.1",
    ]
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 0, res.output
    assert "http://127.0.0.1:8000/" in res.output  # where to see it in the web page
    assert "time per phase: video" in res.output and "· train " in res.output and "· render " in res.output
    image = np.asarray(Image.open(out))
    assert image.shape == (256, 4 * 256, 3)
    for panel in np.split(image, 4, axis=1):  # every panel shows something on the white background
        assert (panel.astype(int).sum(-1) < 3 * 240).mean() > 0.02
    assert (work / "signer.mp4").is_file()
    # The avatar performing someone else's video, beside it: all 12 driving frames, 256 px high.
    from eva_engine.data import read_video

    clip = read_video(mp4)
    assert clip.frames.shape == (12, 256, 512, 3)
    assert np.abs(np.diff(clip.frames[..., 256:, :].astype(int), axis=0)).mean() > 0.5
    avatars = list((work / "service" / "avatars").iterdir())
    assert len(avatars) == 1 and (avatars[0] / "avatar.ply").is_file()
    res = CliRunner().invoke(app, ["demo", "--out", str(tmp_path / "x.jpg")])
    assert res.exit_code == 2
