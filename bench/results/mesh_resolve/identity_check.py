"""Both versions of the mesh renderer on the same scenes: every output equal, bit for bit.
``python identity_check.py <folder holding the old eva_engine/render/mesh.py as mesh_old.py>``."""

import sys

import numpy as np
import torch

from eva_engine.align.face_mesh import head_camera
from eva_engine.body import load_body_model
from eva_engine.render import mesh as new
from eva_engine.synth.texture import Look, apply_look

sys.path.insert(0, sys.argv[1])
import mesh_old as old  # noqa: E402

FIELDS = ("rgb", "alpha", "depth", "face_id", "face_id_samples")
model = load_body_model("anny")
vertices = model(model.default_params(1)).vertices[0].detach()
identical = True
for size, supersample, background in ((512, 2, (1, 1, 1)), (200, 3, (0.1, 0.7, 0.3)), (128, 1, (0, 0, 0))):
    outputs = []
    for module in (old, new):
        config = module.MeshRenderConfig(
            width=size, height=size, supersample=supersample, background=background
        )
        with module.MeshRenderer(model.faces, config, num_vertices=model.num_vertices) as renderer:
            look = Look.random(np.random.default_rng([0, 1]))
            apply_look(renderer, model, model.default_params(1), look, 1024)
            views = [head_camera(model, yaw, 0.0, size) for yaw in (0.0, 40.0, 170.0)]
            outputs.append([renderer.render(vertices, view, K) for K, view in views])
    for a, b in zip(*outputs, strict=True):
        same = all(torch.equal(getattr(a, f), getattr(b, f)) for f in FIELDS)
        identical &= same
        print(size, supersample, same)
print("ALL IDENTICAL" if identical else "DIFFERENT")
