"""A textured triangle-mesh rasterizer for ground-truth images: OpenGL through moderngl on Mesa's
software EGL (llvmpipe), so it runs headless on CPU. It is deliberately a different image
formation model from the Gaussian rasterizer the avatar is trained with.

Per frame it gives shaded colour (Lambert diffuse plus an optional Blinn-Phong highlight whose
strength comes from the texture's alpha channel), coverage (alpha), camera depth and the id of the
triangle seen at each pixel (``gl_PrimitiveID``), with supersampling for anti-aliased edges. The
light is fixed to the camera or to the world (``MeshRenderConfig.light_frame``): in the world, the
shading of a surface changes as the body moves and as the camera moves around it.

Conventions (the project's): OpenCV camera, ``viewmat [4, 4]`` world->camera (x right, y down,
z forward), ``K [3, 3]`` in pixels, pixel (x, y) has its centre at (x + 0.5, y + 0.5).

System requirement: Debian packages ``libegl1 libgl1 libegl-mesa0 libgl1-mesa-dri``
(``scripts/install-system-deps.sh``); without them :class:`MeshRenderer` raises
:class:`MeshRenderError` saying so.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import torch

from eva_engine.geometry import vertex_normals

SYSTEM_PACKAGES = "libegl1 libgl1 libegl-mesa0 libgl1-mesa-dri"

_VERTEX_SHADER = """
#version 330
uniform mat4 view;      // world -> camera (OpenCV)
uniform vec4 intr;      // fx, fy, cx, cy in (supersampled) pixels
uniform float skew;
uniform vec2 size;      // width, height in (supersampled) pixels
uniform vec2 clip;      // near, far
in vec3 in_pos;
in vec3 in_normal;
in vec3 in_color;
in vec2 in_uv;
out vec3 v_normal;
out vec3 v_cam;
out vec3 v_color;
out vec2 v_uv;
void main() {
    vec4 pc = view * vec4(in_pos, 1.0);
    float z = pc.z;
    // Pixel coordinates times z; NDC = 2 px / size - 1, so image row 0 is GL row 0 (no flip).
    float u = intr.x * pc.x + skew * pc.y + intr.z * z;
    float v = intr.y * pc.y + intr.w * z;
    float n = clip.x, f = clip.y;
    gl_Position = vec4(2.0 * u / size.x - z, 2.0 * v / size.y - z, (z * (f + n) - 2.0 * f * n) / (f - n), z);
    v_normal = mat3(view) * in_normal;
    v_cam = pc.xyz;
    v_color = in_color;
    v_uv = in_uv;
}
"""

_FRAGMENT_SHADER = """
#version 330
uniform sampler2D tex;
uniform bool use_texture;
uniform vec3 light;      // unit direction towards the light, camera frame
uniform float ambient;
uniform float shininess; // Blinn-Phong exponent; highlight strength = texture alpha
in vec3 v_normal;
in vec3 v_cam;
in vec3 v_color;
in vec2 v_uv;
layout(location = 0) out vec4 f_color;
layout(location = 1) out int f_id;
layout(location = 2) out float f_depth;
void main() {
    float len = length(v_normal);
    vec3 n = len > 1e-8 ? v_normal / len : vec3(0.0, 0.0, -1.0);
    if (dot(n, v_cam) > 0.0) n = -n;  // two-sided: shade the side facing the camera
    vec4 texel = use_texture ? texture(tex, v_uv) : vec4(v_color, 0.0);
    float shade = ambient + (1.0 - ambient) * max(dot(n, light), 0.0);
    vec3 half_dir = normalize(light - normalize(v_cam));
    float highlight = dot(n, light) > 0.0 ? texel.a * pow(max(dot(n, half_dir), 0.0), shininess) : 0.0;
    f_color = vec4(texel.rgb * shade + vec3(highlight), 1.0);
    f_id = gl_PrimitiveID + 1;  // 0 = background
    f_depth = v_cam.z;
}
"""

_BAKE_VERTEX_SHADER = """
#version 330
in vec2 in_uv;
in vec4 in_attr;
out vec4 v_attr;
void main() {
    gl_Position = vec4(2.0 * in_uv - 1.0, 0.0, 1.0);
    v_attr = in_attr;
}
"""

_BAKE_FRAGMENT_SHADER = """
#version 330
in vec4 v_attr;
layout(location = 0) out vec4 f_attr;
layout(location = 1) out int f_id;
void main() {
    f_attr = v_attr;
    f_id = gl_PrimitiveID + 1;
}
"""


class MeshRenderError(RuntimeError):
    """No usable OpenGL context (missing system libraries) or a failed render."""


@dataclasses.dataclass(frozen=True)
class MeshRenderConfig:
    """Image size and look of :class:`MeshRenderer`."""

    width: int = 512
    height: int = 512
    supersample: int = 2
    """Samples per pixel along each axis; coverage and colour are box-averaged over them."""
    background: tuple[float, float, float] = (1.0, 1.0, 1.0)
    ambient: float = 0.35
    """Fraction of the albedo seen with no direct light (the rest is Lambert from ``light``)."""
    light: tuple[float, float, float] = (-0.35, -0.55, -1.0)
    """Direction towards the light, in the frame ``light_frame`` names (default, in camera
    coordinates: above-left of the camera)."""
    light_frame: str = "camera"
    """"camera" (the light moves with the camera) or "world" (a fixed direction in world
    coordinates: Y up, the subject faces +Z; e.g. (-0.35, 0.55, 1.0) is the camera default seen
    from a front camera)."""
    shininess: float = 24.0
    """Blinn-Phong exponent of the highlight (its strength is the texture's alpha channel)."""
    near: float = 0.01
    far: float = 100.0

    def __post_init__(self) -> None:
        if self.width < 1 or self.height < 1 or self.supersample < 1:
            raise ValueError("width, height and supersample must be >= 1")
        if not 0.0 <= self.ambient <= 1.0:
            raise ValueError(f"ambient must be in [0, 1], got {self.ambient}")
        if not 0.0 < self.near < self.far:
            raise ValueError("need 0 < near < far")
        if self.light_frame not in ("camera", "world"):
            raise ValueError(f"light_frame must be 'camera' or 'world', got {self.light_frame!r}")


@dataclasses.dataclass
class MeshRenderOutput:
    """One rendered frame. rgb: [H, W, 3] float32 (background where alpha is 0); alpha: [H, W]
    coverage in [0, 1]; depth: [H, W] camera z of the triangle seen at the pixel (0 where none);
    face_id: [H, W] int64 triangle index (-1 where none), both taken from the covered sample
    nearest the pixel centre; face_id_samples: [H*s, W*s] int64, every sample's triangle."""

    rgb: torch.Tensor
    alpha: torch.Tensor
    depth: torch.Tensor
    face_id: torch.Tensor
    face_id_samples: torch.Tensor

    @property
    def supersample(self) -> int:
        return self.face_id_samples.shape[0] // self.face_id.shape[0]

    def label_coverage(self, face_labels: torch.Tensor, label: int) -> torch.Tensor:
        """Coverage [H, W] of the triangles whose ``face_labels [F]`` equal ``label``
        (a part's visible pixels after occlusion; never more than ``alpha``)."""
        ids = self.face_id_samples.numpy()
        labels = np.asarray(face_labels.cpu() if isinstance(face_labels, torch.Tensor) else face_labels)
        hit = (ids >= 0) & (labels[np.maximum(ids, 0)] == label)
        s = self.supersample
        h, w = self.face_id.shape
        return torch.from_numpy(
            hit.reshape(h, s, w, s).mean(axis=(1, 3), dtype=np.float64).astype(np.float32)
        )


def _create_context():
    import moderngl

    try:
        return moderngl.create_standalone_context(backend="egl")
    except Exception as err:
        raise MeshRenderError(
            f"cannot create an OpenGL context on Mesa's software EGL ({err}). Install the system "
            f"packages: apt-get install {SYSTEM_PACKAGES} (scripts/install-system-deps.sh)"
        ) from err


class MeshRenderer:
    """Renders one mesh topology (``faces [F, 3]``) many times. Use as a context manager (or
    call :meth:`close`) to free the GL context.

    Surface: :meth:`set_surface` with per-vertex ``colors [V, 3]``, or a ``texture [Ht, Wt, 3]``
    with texture coordinates ``uv [T, 2]`` and per-corner indices ``face_uv [F, 3]`` (seams
    have their own coordinates); colours are albedo in [0, 1], shaded by Lambert.
    """

    def __init__(
        self, faces, config: MeshRenderConfig | None = None, num_vertices: int | None = None
    ) -> None:
        self.config = config or MeshRenderConfig()
        f = np.asarray(faces.cpu() if isinstance(faces, torch.Tensor) else faces, dtype=np.int64)
        if f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
            raise ValueError(f"faces must be [F, 3] with F > 0, got {f.shape}")
        self.faces = f
        self.num_vertices = int(num_vertices if num_vertices is not None else f.max() + 1)
        if f.min() < 0 or f.max() >= self.num_vertices:
            raise ValueError("faces index vertices outside 0..num_vertices-1")
        self._corners = f.reshape(-1)
        self.ctx = _create_context()
        ctx = self.ctx
        try:
            c = self.config
            s = c.supersample
            self._size = (c.width * s, c.height * s)
            self._color = ctx.texture(self._size, 4, dtype="f4")
            self._ids = ctx.texture(self._size, 1, dtype="i4")
            self._depth = ctx.texture(self._size, 1, dtype="f4")
            self._zbuf = ctx.depth_renderbuffer(self._size)
            self._fbo = ctx.framebuffer([self._color, self._ids, self._depth], self._zbuf)
            self._prog = ctx.program(vertex_shader=_VERTEX_SHADER, fragment_shader=_FRAGMENT_SHADER)
            n = len(self._corners)
            self._pos = ctx.buffer(reserve=n * 12, dynamic=True)
            self._nrm = ctx.buffer(reserve=n * 12, dynamic=True)
            self._col = ctx.buffer(reserve=n * 12)
            self._uv = ctx.buffer(reserve=n * 8)
            self._texture = None
            self._vao = ctx.vertex_array(
                self._prog,
                [
                    (self._pos, "3f", "in_pos"),
                    (self._nrm, "3f", "in_normal"),
                    (self._col, "3f", "in_color"),
                    (self._uv, "2f", "in_uv"),
                ],
            )
            light = np.asarray(c.light, dtype=np.float64)
            self._light = light / np.linalg.norm(light)
            self._prog["light"].value = tuple(self._light)
            self._prog["ambient"].value = float(c.ambient)
            self._prog["shininess"].value = float(c.shininess)
            self._prog["clip"].value = (c.near, c.far)
            self._prog["size"].value = (float(self._size[0]), float(self._size[1]))
            self.set_surface(colors=np.full((self.num_vertices, 3), 0.7, np.float32))
        except Exception:
            ctx.release()
            raise

    # -- lifetime ----------------------------------------------------------------------------
    def close(self) -> None:
        if self.ctx is not None:
            self.ctx.release()
            self.ctx = None

    def __enter__(self) -> MeshRenderer:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # -- surface -----------------------------------------------------------------------------
    def set_surface(self, colors=None, texture=None, uv=None, face_uv=None) -> None:
        """Per-vertex ``colors [V, 3]``, or ``texture [Ht, Wt, 3 or 4]`` (uint8 or float in
        [0, 1], row 0 at v = 0; a 4th channel is the highlight strength, else none) with
        ``uv [T, 2]`` and ``face_uv [F, 3]`` (default: ``faces``)."""
        if (colors is None) == (texture is None):
            raise ValueError("give either colors or texture")
        n = len(self._corners)
        if colors is not None:
            col = np.asarray(colors, dtype=np.float32)
            if col.shape != (self.num_vertices, 3):
                raise ValueError(f"colors must be [{self.num_vertices}, 3], got {col.shape}")
            self._col.write(np.ascontiguousarray(col[self._corners]).tobytes())
            self._uv.write(np.zeros((n, 2), np.float32).tobytes())
            self._prog["use_texture"].value = False
            return
        uv = np.asarray(uv, dtype=np.float32)
        fuv = self.faces if face_uv is None else np.asarray(face_uv, dtype=np.int64)
        if fuv.shape != self.faces.shape or uv.ndim != 2 or uv.shape[1] != 2 or fuv.max() >= len(uv):
            raise ValueError("uv must be [T, 2] and face_uv [F, 3] indexing it")
        tex = np.asarray(texture)
        if tex.ndim != 3 or tex.shape[2] not in (3, 4):
            raise ValueError(f"texture must be [Ht, Wt, 3 or 4], got {tex.shape}")
        tex = tex if tex.dtype == np.uint8 else np.clip(np.round(tex * 255.0), 0, 255).astype(np.uint8)
        if tex.shape[2] == 3:  # no highlight
            tex = np.concatenate([tex, np.zeros_like(tex[..., :1])], axis=2)
        if self._texture is not None:
            self._texture.release()
        self._texture = self.ctx.texture((tex.shape[1], tex.shape[0]), 4, np.ascontiguousarray(tex).tobytes())
        self._texture.build_mipmaps()
        import moderngl

        self._texture.filter = (moderngl.LINEAR_MIPMAP_LINEAR, moderngl.LINEAR)
        self._texture.anisotropy = 8.0
        self._texture.use(0)
        self._prog["tex"].value = 0
        self._uv.write(np.ascontiguousarray(uv[fuv.reshape(-1)]).tobytes())
        self._col.write(np.zeros((n, 3), np.float32).tobytes())
        self._prog["use_texture"].value = True

    # -- rendering ---------------------------------------------------------------------------
    def render(self, vertices, viewmat, K, normals=None) -> MeshRenderOutput:
        """Render posed ``vertices [V, 3]`` (world) with camera ``viewmat [4, 4]``, ``K [3, 3]``.
        ``normals [V, 3]`` default to :func:`vertex_normals`."""
        if self.ctx is None:
            raise MeshRenderError("the renderer is closed")
        v = np.asarray(
            vertices.detach().cpu() if isinstance(vertices, torch.Tensor) else vertices, np.float32
        )
        if v.shape != (self.num_vertices, 3):
            raise ValueError(f"vertices must be [{self.num_vertices}, 3], got {list(v.shape)}")
        if not np.isfinite(v).all():
            raise ValueError("vertices contain NaN or Inf")
        view = np.asarray(torch.as_tensor(viewmat).detach().cpu(), np.float64)
        K_ = np.asarray(torch.as_tensor(K).detach().cpu(), np.float64)
        if (
            view.shape != (4, 4)
            or K_.shape != (3, 3)
            or not (np.isfinite(view).all() and np.isfinite(K_).all())
        ):
            raise ValueError("viewmat must be a finite [4, 4] and K a finite [3, 3]")
        n = vertex_normals(v, self.faces) if normals is None else np.asarray(normals, np.float32)
        s = self.config.supersample
        self._pos.write(np.ascontiguousarray(v[self._corners]).tobytes())
        self._nrm.write(np.ascontiguousarray(n[self._corners]).tobytes())
        self._prog["view"].write(np.ascontiguousarray(view.T, dtype=np.float32).tobytes())  # column-major
        self._prog["intr"].value = (s * K_[0, 0], s * K_[1, 1], s * K_[0, 2], s * K_[1, 2])
        if self.config.light_frame == "world":
            self._prog["light"].value = tuple(view[:3, :3] @ self._light)
        self._prog["skew"].value = float(s * K_[0, 1])

        import moderngl

        self._fbo.use()
        self._fbo.viewport = (0, 0, *self._size)
        self._fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
        self.ctx.enable(moderngl.DEPTH_TEST)
        self.ctx.disable(moderngl.CULL_FACE)
        self._vao.render(moderngl.TRIANGLES)
        ws, hs = self._size
        color = np.frombuffer(self._fbo.read(components=3, attachment=0, dtype="f4"), np.float32)
        ids = np.frombuffer(self._fbo.read(components=1, attachment=1, dtype="i4"), np.int32)
        depth = np.frombuffer(self._fbo.read(components=1, attachment=2, dtype="f4"), np.float32)
        color = color.reshape(hs, ws, 3)
        ids = ids.reshape(hs, ws).astype(np.int64) - 1
        depth = depth.reshape(hs, ws)
        return self._resolve(color, ids, depth)

    def _resolve(self, color: np.ndarray, ids: np.ndarray, depth: np.ndarray) -> MeshRenderOutput:
        """Box-filter the samples into pixels."""
        c, s = self.config, self.config.supersample
        h, w = c.height, c.width
        bg = np.asarray(c.background, np.float32)
        covered = ids >= 0
        # Each pixel's s x s samples summed slice by slice in float64, an uncovered sample as the
        # background: float32 samples add there without rounding (unless they differ by over
        # 2^25), so this is numpy's float64 mean of each block, to the bit on every scene tried,
        # without its slow reduction over a strided 5-D view (a third of a render before).
        # Uncovered samples hold the clear colour 0 (``render``), so they add nothing.
        count = np.zeros((h, w), np.int64)
        total = np.zeros((h, w, 3), np.float64)
        for a in range(s):
            for b in range(s):
                count += covered[a::s, b::s]
                total += color[a::s, b::s]
        total += (s * s - count)[..., None] * bg.astype(np.float64)
        alpha = (count / (s * s)).astype(np.float32)
        rgb = (total / (s * s)).astype(np.float32)
        rgb = np.where(alpha[..., None] > 0, np.clip(rgb, 0.0, 1.0), bg)  # exact background
        # Per-pixel id and depth from the covered sample nearest the centre.
        offsets = sorted(
            ((a, b) for a in range(s) for b in range(s)),
            key=lambda ab: ((ab[0] + 0.5 - s / 2) ** 2 + (ab[1] + 0.5 - s / 2) ** 2, ab),
        )
        face = np.full((h, w), -1, np.int64)
        z = np.zeros((h, w), np.float32)
        for a, b in reversed(offsets):
            sid = ids[a::s, b::s]
            hit = sid >= 0
            face = np.where(hit, sid, face)
            z = np.where(hit, depth[a::s, b::s], z)
        return MeshRenderOutput(
            rgb=torch.from_numpy(np.ascontiguousarray(rgb)),
            alpha=torch.from_numpy(alpha),
            depth=torch.from_numpy(z),
            face_id=torch.from_numpy(face),
            face_id_samples=torch.from_numpy(ids),
        )

    # -- texture baking ------------------------------------------------------------------------
    def bake(self, uv, face_uv, attributes, size: int) -> tuple[np.ndarray, np.ndarray]:
        """Rasterize the mesh in texture space: per texel of a ``size x size`` texture, the
        barycentric interpolation of per-vertex ``attributes [V, A]`` (A <= 4) and the triangle
        id (-1 where no triangle maps). Returns ([size, size, A] float32, [size, size] int64),
        row 0 at v = 0 (the layout :meth:`set_surface` expects)."""
        if self.ctx is None:
            raise MeshRenderError("the renderer is closed")
        import moderngl

        attr = np.asarray(attributes, np.float32)
        a = attr.shape[1]
        if attr.shape[0] != self.num_vertices or not 1 <= a <= 4:
            raise ValueError(f"attributes must be [{self.num_vertices}, A<=4], got {attr.shape}")
        attr4 = np.zeros((self.num_vertices, 4), np.float32)
        attr4[:, :a] = attr
        uv = np.asarray(uv, np.float32)
        fuv = np.asarray(face_uv, np.int64).reshape(-1)
        ctx = self.ctx
        prog = ctx.program(vertex_shader=_BAKE_VERTEX_SHADER, fragment_shader=_BAKE_FRAGMENT_SHADER)
        buf_uv = ctx.buffer(np.ascontiguousarray(uv[fuv]).tobytes())
        buf_attr = ctx.buffer(np.ascontiguousarray(attr4[self._corners]).tobytes())
        vao = ctx.vertex_array(prog, [(buf_uv, "2f", "in_uv"), (buf_attr, "4f", "in_attr")])
        out_attr = ctx.texture((size, size), 4, dtype="f4")
        out_id = ctx.texture((size, size), 1, dtype="i4")
        fbo = ctx.framebuffer([out_attr, out_id])
        try:
            fbo.use()
            fbo.viewport = (0, 0, size, size)
            fbo.clear(0.0, 0.0, 0.0, 0.0)
            ctx.disable(moderngl.DEPTH_TEST)
            vao.render(moderngl.TRIANGLES)
            values = np.frombuffer(fbo.read(components=4, attachment=0, dtype="f4"), np.float32)
            ids = np.frombuffer(fbo.read(components=1, attachment=1, dtype="i4"), np.int32)
        finally:
            for obj in (fbo, out_attr, out_id, vao, buf_uv, buf_attr, prog):
                obj.release()
        values = values.reshape(size, size, 4)[..., :a].copy()
        return values, ids.reshape(size, size).astype(np.int64) - 1
