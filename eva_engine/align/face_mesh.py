"""Dense face fitting: a fixed correspondence between MediaPipe's 478 face-mesh landmarks and
points on the body model's face surface, computed by the project itself.

How the correspondence is made (:func:`build_correspondence`, once, then cached beside the Anny
cache; the default Anny's ships in the package, ``SHIPPED_DIR``): the neutral subject is rendered
with the synthetic benchmark's painted face (eyes, brows, lids, lips: what the face mesh needs to
lock on) by the triangle-mesh renderer, seen head on and turned up to 20 degrees; MediaPipe
FaceMesh (static images, refined irises) runs on each render; each landmark's pixel gives the
triangle seen there and the barycentric coordinates of that pixel in the triangle's projection,
i.e. a point on the rest surface. Per landmark the views are combined by the median 3D point, and
the view's candidate nearest to it is kept. A landmark is kept (``valid``) when it was found in
most views, the views agree to within ``max_spread`` metres, it lies on a face triangle, and it is
not on the face's silhouette oval (those points slide along the outline as the head turns, so no
surface point matches them), and it is not one of the ten iris points (gaze is not what the painted
eyes pin down).

Two places where the pixel alone picks the wrong surface (version 2): the lid landmarks sit on
the edge of the lid, where the pixel often shows the eyeball, a separate mesh that no blink
moves; and with the mouth closed the inner-lip landmarks of both lips meet on one seam, so the
lower lip's points landed on the upper lip and no jaw opening moved them apart. So a landmark
only takes skin (the mesh's largest connected piece): on another piece it takes the nearest
skin pixel; and the inner-lip landmarks come from renders with the jaw open
(``INNER_LIP_EXPRESSION``), where each lip shows its own edge.

Fitting then uses, per frame, the detected landmarks against the projected correspondence
points (``BodyModel.posed_points``), which moves the expression (jaw, lips, lids, brows through
the facial actions) where 16 sparse points could not.
"""

from __future__ import annotations

import gzip
import hashlib
import json
import logging
import math
from collections.abc import Callable, Iterator
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import TypeVar

import numpy as np
import torch
from torch import Tensor

from eva_engine import paths
from eva_engine.body.keypoints import KeypointRegressor
from eva_engine.body.model import SIDED_PART_NAMES, BodyModel
from eva_engine.geometry import project_points, to_camera
from eva_engine.render import intrinsics, look_at
from eva_engine.render.mesh import MeshRenderConfig, MeshRenderer
from eva_engine.synth.texture import Look, apply_look

logger = logging.getLogger(__name__)
T = TypeVar("T")

NUM_LANDMARKS = 478
IRIS_START = 468  # the refined iris points: gaze, which the painted eyes do not pin down
VERSION = 2
FILE_NAME = "face_mesh_correspondence.json"
VIEWS_DEG = tuple((yaw, pitch) for yaw in (-20.0, -10.0, 0.0, 10.0, 20.0) for pitch in (-10.0, 0.0, 10.0))
INNER_LIPS = (78, 191, 80, 81, 82, 13, 312, 311, 310, 415, 308, 324, 318, 402, 317, 14, 87, 178, 88, 95)
"""MediaPipe's inner-lip contour (upper: 191 ... 415; lower: 324 ... 95; corners 78 and 308)."""
INNER_LIP_EXPRESSION = {"jawOpen": 0.35}
"""The facial actions of the renders the inner-lip landmarks come from: lips apart, the mouth's
inside still shadowed enough for the face mesh to find both edges."""
OPENING_PAIRS = (
    *((160, 144), (159, 145), (158, 153)),  # right eye: upper lid, lower lid
    *((385, 380), (386, 374), (387, 373)),  # left eye
    *((81, 178), (82, 87), (13, 14), (312, 317), (311, 402)),  # inner lips: upper, lower
)
"""Landmark pairs across the lids and the inner lips: their differences are the eye and mouth
openings that the fit's opening term (``FitStage.w_openings``) matches."""
SKIN_SEARCH_PX = 12
"""How far (pixels of the 512 px render) a landmark on a non-skin piece looks for skin."""


@dataclass(frozen=True)
class FaceMeshCorrespondence:
    """Per MediaPipe landmark: ``faces [478]`` triangle index, ``barycentric [478, 3]``, ``valid
    [478]`` (use it in fitting), ``spread [478]`` metres between views."""

    faces: Tensor
    barycentric: Tensor
    valid: Tensor
    spread: Tensor

    def vertex_terms(self, model_faces: Tensor) -> dict[int, dict[int, float]]:
        """{landmark: {vertex: weight}} for the valid landmarks (weights sum to 1)."""
        out: dict[int, dict[int, float]] = {}
        for k in torch.nonzero(self.valid).squeeze(1).tolist():
            tri = model_faces[self.faces[k]].tolist()
            terms: dict[int, float] = {}
            for v, w in zip(tri, self.barycentric[k].tolist(), strict=True):
                terms[int(v)] = terms.get(int(v), 0.0) + float(w)
            out[k] = terms
        return out

    def regressor(self, model: BodyModel) -> tuple[KeypointRegressor, Tensor]:
        """(regressor of the valid landmarks' surface points, on the model's device, for
        ``BodyModel.posed_points``; ``landmarks [L]`` their MediaPipe indices, in its order)."""
        terms = self.vertex_terms(model.faces.cpu())
        names = [f"face_mesh_{k}" for k in terms]
        vertex_terms = dict(zip(names, terms.values(), strict=True))
        reg = KeypointRegressor(names, vertex_terms, {}, model.num_joints)
        return reg.to(model.device), torch.tensor(list(terms), dtype=torch.int64)

    def to_json(self) -> dict:
        return {
            "version": VERSION,
            "faces": self.faces.tolist(),
            "barycentric": self.barycentric.tolist(),
            "valid": self.valid.tolist(),
            "spread": self.spread.tolist(),
        }

    @classmethod
    def from_json(cls, d: dict) -> FaceMeshCorrespondence:
        return cls(
            torch.tensor(d["faces"], dtype=torch.int64),
            torch.tensor(d["barycentric"], dtype=torch.float32),
            torch.tensor(d["valid"], dtype=torch.bool),
            torch.tensor(d["spread"], dtype=torch.float32),
        )


def face_oval() -> set[int]:
    """MediaPipe's face-oval (silhouette) landmark indices."""
    from mediapipe.python.solutions import face_mesh

    return {i for edge in face_mesh.FACEMESH_FACE_OVAL for i in edge}


def head_camera(model: BodyModel, yaw_deg: float, pitch_deg: float, size: int) -> tuple[Tensor, Tensor]:
    """(K, viewmat) of a close-up of the rest-pose face: 0.6 m away, turned by yaw / pitch about
    the face's centre, the head filling most of the image."""
    with torch.no_grad():
        kp = model.keypoints(model(model.default_params(1)))[0]
    names = list(model.keypoint_names)
    eyes = 0.5 * (kp[names.index("face_left_iris")] + kp[names.index("face_right_iris")])
    mouth = 0.5 * (kp[names.index("face_mouth_left")] + kp[names.index("face_mouth_right")])
    centre = (0.5 * (eyes + mouth)).double()
    yaw, pitch = math.radians(yaw_deg), math.radians(pitch_deg)
    direction = torch.tensor(
        [math.sin(yaw) * math.cos(pitch), math.sin(pitch), math.cos(yaw) * math.cos(pitch)]
    )
    eye = centre + 0.6 * direction.double()
    return intrinsics(size, size, 28.0), look_at(eye.tolist(), centre.tolist())


@contextmanager
def painted_face_renderer(model: BodyModel, size: int = 512) -> Iterator[MeshRenderer]:
    """A ``size``-pixel square mesh renderer of ``model`` wearing the synthetic benchmark's painted
    face (one fixed look: every render the correspondence and its calibration are made from)."""
    config = MeshRenderConfig(width=size, height=size, supersample=2)
    with MeshRenderer(model.faces, config, num_vertices=model.num_vertices) as renderer:
        apply_look(renderer, model, model.default_params(1), Look.random(np.random.default_rng([0, 1])), 2048)
        yield renderer


@contextmanager
def shared_painted_face(model: BodyModel) -> Iterator[Callable[[], MeshRenderer]]:
    """A function that opens the 512-pixel painted-face renderer on its first call and returns
    that one after, closed on exit: the correspondence and its calibration build from one
    renderer, whose texture bake (about 5 s) would otherwise run once for each."""
    with ExitStack() as stack:
        yield cache(lambda: stack.enter_context(painted_face_renderer(model, 512)))


def render_face(
    model: BodyModel,
    views: tuple[tuple[float, float], ...],
    size: int = 512,
    expression: dict[str, float] | None = None,
    renderer: MeshRenderer | None = None,
) -> list[dict]:
    """The painted face from each (yaw, pitch) view, neutral or with ``expression`` ({facial
    action: value}): dicts with rgb [H, W, 3] uint8, face_id [H, W], K, viewmat, the rendered
    vertices [V, 3] and the neutral ones, ``rest`` [V, 3] (the same without an expression).
    ``renderer``: an open :func:`painted_face_renderer` of ``size`` (else one is opened)."""
    params = model.params_from_pose({"expression": expression or {}})
    with torch.no_grad():
        rest = model(model.default_params(1)).vertices[0]
        vertices = model(params).vertices[0] if expression else rest
    out = []
    with ExitStack() as stack:
        if renderer is None:
            renderer = stack.enter_context(painted_face_renderer(model, size))
        for yaw, pitch in views:
            K, view = head_camera(model, yaw, pitch, size)
            r = renderer.render(vertices, view, K)
            rgb = (r.rgb.numpy() * 255 + 0.5).astype(np.uint8)
            out.append(
                {
                    "rgb": rgb,
                    "face_id": r.face_id,
                    "K": K,
                    "viewmat": view,
                    "vertices": vertices,
                    "rest": rest,
                }
            )
    return out


def skin_faces(faces: np.ndarray, num_vertices: int) -> np.ndarray:
    """[T] bool: the triangles of the mesh's largest connected piece (Anny's skin; its eyeballs
    and mouth parts are pieces of their own). faces: [T, 3] vertex indices."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    rows = np.concatenate([faces[:, 0], faces[:, 1], faces[:, 2]])
    cols = np.concatenate([faces[:, 1], faces[:, 2], faces[:, 0]])
    graph = coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(num_vertices, num_vertices))
    _, label = connected_components(graph, directed=False)
    skin = np.bincount(label[faces[:, 0]]).argmax()
    return label[faces[:, 0]] == skin


def nearest_skin_pixel(
    face_id: np.ndarray, skin: np.ndarray, x: float, y: float, radius: int
) -> tuple | None:
    """(col, row) of the pixel nearest to (x, y) that shows a skin triangle, within ``radius``
    pixels, or None. face_id: [H, W] triangle per pixel (-1: none); skin: [T] bool."""
    h, w = face_id.shape
    c0, r0 = int(np.floor(x)), int(np.floor(y))
    rows = np.arange(max(r0 - radius, 0), min(r0 + radius + 1, h))
    cols = np.arange(max(c0 - radius, 0), min(c0 + radius + 1, w))
    if not len(rows) or not len(cols):
        return None
    ids = face_id[np.ix_(rows, cols)]
    ok = ids >= 0
    ok[ok] = skin[ids[ok]]
    if not ok.any():
        return None
    rr, cc = np.meshgrid(rows, cols, indexing="ij")
    d = (cc + 0.5 - x) ** 2 + (rr + 0.5 - y) ** 2
    d[~ok] = np.inf
    k = np.unravel_index(int(d.argmin()), d.shape)
    if d[k] > radius**2:
        return None
    return int(cc[k]), int(rr[k])


def detect_face_mesh(rgb: np.ndarray) -> np.ndarray | None:
    """MediaPipe FaceMesh on one RGB uint8 image: [478, 2] pixel coordinates, or None."""
    from mediapipe.python.solutions import face_mesh

    with face_mesh.FaceMesh(static_image_mode=True, max_num_faces=1, refine_landmarks=True) as fm:
        return face_mesh_pixels(fm, rgb)


def face_mesh_pixels(detector, rgb: np.ndarray) -> np.ndarray | None:
    """An open MediaPipe ``FaceMesh`` (static images, refined irises) on one RGB uint8 image:
    [478, 2] pixel coordinates, or None."""
    result = detector.process(np.ascontiguousarray(rgb))
    if not result.multi_face_landmarks:
        return None
    h, w = rgb.shape[:2]
    pts = np.array([(p.x * w, p.y * h) for p in result.multi_face_landmarks[0].landmark], dtype=np.float64)
    return pts if len(pts) == NUM_LANDMARKS else None


def _barycentric(p: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """Barycentric coordinates [3] of 2D point p in 2D triangle tri [3, 2] (clamped inside)."""
    a, b, c = tri
    m = np.array([b - a, c - a]).T
    if abs(np.linalg.det(m)) < 1e-12:
        return np.array([1 / 3, 1 / 3, 1 / 3])
    u, v = np.linalg.solve(m, p - a)
    bary = np.clip(np.array([1 - u - v, u, v]), 0.0, 1.0)
    return bary / bary.sum()


def build_correspondence(
    model: BodyModel,
    views: tuple[tuple[float, float], ...] = VIEWS_DEG,
    max_spread: float = 0.004,
    renderer: MeshRenderer | None = None,
) -> FaceMeshCorrespondence:
    """The correspondence of ``model`` (module docstring). Needs the mesh renderer (EGL) and
    MediaPipe; takes a few seconds. ``renderer``: an open 512-pixel :func:`painted_face_renderer`
    (else one is opened for both sets of renders)."""
    faces = model.faces.cpu().numpy()
    face_part = model.sided_part_ids.cpu().numpy()
    face_index = SIDED_PART_NAMES.index("face")
    skin = skin_faces(faces, model.num_vertices)
    inner_lips = set(INNER_LIPS)
    candidates: list[list[tuple[int, np.ndarray, np.ndarray]]] = [[] for _ in range(NUM_LANDMARKS)]
    with ExitStack() as stack:
        if renderer is None:
            renderer = stack.enter_context(painted_face_renderer(model, 512))
        renders = [(r, False) for r in render_face(model, views, renderer=renderer)]
        renders += [
            (r, True) for r in render_face(model, views, expression=INNER_LIP_EXPRESSION, renderer=renderer)
        ]
    for r, open_mouth in renders:
        pts = detect_face_mesh(r["rgb"])
        if pts is None:
            continue
        cam = to_camera(r["vertices"][None].double(), r["viewmat"].double())
        uv = project_points(cam, r["K"].double())[0].numpy()
        face_id = r["face_id"].numpy()
        h, w = face_id.shape
        rest = r["rest"].double().numpy()
        for k, (x, y) in enumerate(pts):
            if (k in inner_lips) != open_mouth:
                continue
            col, row = int(np.floor(x)), int(np.floor(y))
            if not (0 <= col < w and 0 <= row < h) or face_id[row, col] < 0:
                continue
            if not skin[face_id[row, col]]:
                found = nearest_skin_pixel(face_id, skin, x, y, SKIN_SEARCH_PX)
                if found is None:
                    continue
                col, row = found
                x, y = col + 0.5, row + 0.5
            f = int(face_id[row, col])
            bary = _barycentric(np.array([x, y]), uv[faces[f]])
            candidates[k].append((f, bary, bary @ rest[faces[f]]))
    oval = face_oval()
    tri = torch.zeros(NUM_LANDMARKS, dtype=torch.int64)
    bary_out = torch.full((NUM_LANDMARKS, 3), 1 / 3)
    valid = torch.zeros(NUM_LANDMARKS, dtype=torch.bool)
    spread = torch.full((NUM_LANDMARKS,), float("inf"))
    for k, cands in enumerate(candidates):
        if not cands:
            continue
        points = np.stack([c[2] for c in cands])
        median = np.median(points, axis=0)
        dist = np.linalg.norm(points - median, axis=1)
        best = int(dist.argmin())
        f, bary, _ = cands[best]
        tri[k], bary_out[k] = f, torch.from_numpy(bary).float()
        spread[k] = float(np.median(dist))
        on_face = bool((face_part[faces[f]] == face_index).all())
        valid[k] = (
            len(cands) >= 0.6 * len(views)
            and spread[k] <= max_spread
            and on_face
            and k not in oval
            and k < IRIS_START
        )
    logger.info("face-mesh correspondence: %d of %d landmarks valid", int(valid.sum()), NUM_LANDMARKS)
    return FaceMeshCorrespondence(tri, bary_out, valid, spread)


def cache_key(model: BodyModel) -> str:
    """Changes with the body model's mesh, the MediaPipe version and this module's VERSION."""
    import mediapipe

    h = hashlib.sha256()
    h.update(model.faces.cpu().numpy().tobytes())
    h.update(model.canonical(model.default_params(1))[0].detach().cpu().numpy().round(5).tobytes())
    h.update(f"{mediapipe.__version__}/{VERSION}".encode())
    return h.hexdigest()[:16]


def cache_folder(model: BodyModel, cache_dir: Path | None = None) -> Path:
    """Where ``model``'s own derived files live: ``cache_dir``, else its cache's folder."""
    own = getattr(getattr(model, "config", None), "cache_dir", None)  # where this model's cache is
    return Path(cache_dir or own or paths.cache_dir("anny"))


SHIPPED_DIR = Path(__file__).parent / "shipped"
"""The correspondence and calibration of the default Anny, as ``make face-mesh-files`` built them
(``align.shipped_face_files``): read where their key matches, so a fresh install does not spend
half a minute rendering and detecting faces to make the same files again."""


def cached_json(
    path: Path,
    key: str,
    what: str,
    build: Callable[[], T],
    parse: Callable[[dict], T],
    missing: tuple = (),
    shipped: Path | None = None,
) -> T | None:
    """The object that ``parse`` reads from ``path`` if it was written there for ``key``, else
    from the gzipped ``shipped`` file if that was, else ``build()``'s, written to ``path``
    (``to_json``, atomically) for the next time; None, with a warning, if building raised one of
    ``missing``. An unreadable file is built again."""
    for source in (path, shipped):
        if source is None or not source.is_file():
            continue
        try:
            raw = source.read_bytes()
            doc = json.loads(gzip.decompress(raw) if source.suffix == ".gz" else raw)
            if doc.get("key") == key:
                return parse(doc)
        except (OSError, ValueError, KeyError) as err:
            logger.warning("unreadable %s %s (%s); rebuilding it", what, source, err)
    try:
        built = build()
    except missing as err:
        logger.warning("no %s (%s)", what, err)
        return None
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".partial")
    tmp.write_text(json.dumps({"key": key, **built.to_json()}))
    tmp.replace(path)
    return built


def load_correspondence(
    model: BodyModel, cache_dir: Path | None = None, renderer: Callable[[], MeshRenderer] | None = None
) -> FaceMeshCorrespondence | None:
    """The cached correspondence of ``model`` (built and cached on first use), or None where it
    cannot be made (a model without the painted-face renderer, i.e. not Anny; no MediaPipe: dense
    face fitting is then off). ``renderer``: called for the renderer to build with, if it must
    (:func:`shared_painted_face`)."""
    if model.name != "anny":
        return None
    return cached_json(
        cache_folder(model, cache_dir) / FILE_NAME,
        cache_key(model),
        "face-mesh correspondence",
        lambda: build_correspondence(model, renderer=renderer() if renderer else None),
        FaceMeshCorrespondence.from_json,
        missing=(ImportError,),
        shipped=SHIPPED_DIR / f"{FILE_NAME}.gz",
    )
