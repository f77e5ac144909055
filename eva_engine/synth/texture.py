"""The synthetic subject's look: a procedural albedo texture for Anny, painted in the body's rest
pose and baked into Anny's UV atlas, so the detail moves with the skin.

What is painted, and why (MediaPipe needs shading, clothing unlike skin and a painted face to
find a rendered body; EVA's point is that hands and face carry the hard detail): clothing unlike
skin (a checked shirt with sleeves and a printed chest panel, twill trousers, shoes), a painted
face (hair, eyebrows, lid lines, lips, sclera, iris and pupil, fine skin mottling), hands with a
distinct tint per finger, knuckle creases and nails. The patterns have millimetre-scale lines and
edges, so blur shows up in LPIPS. The texture's alpha channel is the surface's gloss (the
strength of the renderer's highlight): wet eyes, nails and lips shine, cloth barely.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import torch

from eva_engine.body.anny_backend import SEGMENT_LABELS, face_segment_masks
from eva_engine.body.rest_axes import rest_axes
from eva_engine.geometry import vertex_normals

SKIN_TONES = ((0.86, 0.68, 0.57), (0.72, 0.52, 0.39), (0.58, 0.40, 0.28), (0.40, 0.26, 0.18))
SHIRT_COLORS = (
    (0.05, 0.42, 0.40),
    (0.12, 0.20, 0.45),
    (0.50, 0.10, 0.16),
    (0.72, 0.56, 0.12),
    (0.30, 0.45, 0.20),
)
TROUSER_COLORS = ((0.28, 0.21, 0.15), (0.14, 0.18, 0.30), (0.13, 0.13, 0.13))
HAIR_COLORS = ((0.06, 0.05, 0.05), (0.24, 0.15, 0.08), (0.55, 0.43, 0.26))
PRINT_INKS = ((0.95, 0.93, 0.85), (0.98, 0.80, 0.15), (0.90, 0.25, 0.20))
# Highlight strength (texture alpha) per material.
GLOSS = {
    "skin": 0.10,
    "lips": 0.25,
    "eye": 0.8,
    "nail": 0.5,
    "hair": 0.2,
    "shirt": 0.04,
    "print": 0.2,
    "trousers": 0.03,
    "shoes": 0.35,
    "mouth": 0.3,
}
IRIS_COLORS = ((0.30, 0.17, 0.07), (0.22, 0.38, 0.58), (0.28, 0.42, 0.22))
# Multiplicative tint per finger (thumb .. pinky): distinct but still skin.
FINGER_TINTS = (
    (1.07, 0.97, 0.91),
    (0.93, 1.00, 1.07),
    (1.06, 1.04, 0.88),
    (0.92, 0.94, 1.00),
    (1.04, 0.92, 0.98),
)


@dataclasses.dataclass(frozen=True)
class Look:
    """Colours of one subject (albedo, [0, 1] RGB)."""

    skin: tuple[float, float, float]
    shirt: tuple[float, float, float]
    trousers: tuple[float, float, float]
    hair: tuple[float, float, float]
    iris: tuple[float, float, float]
    lips: tuple[float, float, float]
    nails: tuple[float, float, float] = (0.95, 0.80, 0.78)
    shoes: tuple[float, float, float] = (0.10, 0.09, 0.09)
    print_ink: tuple[float, float, float] = (0.95, 0.93, 0.85)

    @classmethod
    def random(cls, rng: np.random.Generator) -> Look:
        def pick(options):
            return tuple(float(x) for x in options[rng.integers(len(options))])

        skin = pick(SKIN_TONES)
        lips = tuple(float(x) for x in np.clip(np.array(skin) * (0.95, 0.55, 0.55) + (0.10, 0.0, 0.0), 0, 1))
        return cls(
            skin=skin,
            shirt=pick(SHIRT_COLORS),
            trousers=pick(TROUSER_COLORS),
            hair=pick(HAIR_COLORS),
            iris=pick(IRIS_COLORS),
            lips=lips,
            print_ink=pick(PRINT_INKS),
        )


def _hash_noise(p: np.ndarray, scale: float, seed: int) -> np.ndarray:
    """Smooth value noise in [0, 1] at points p [N, 3] (metres), feature size ``scale``."""
    if len(p) == 0:
        return np.zeros(0)
    q = p / scale
    i0 = np.floor(q).astype(np.int64)
    f = q - i0
    f = f * f * (3.0 - 2.0 * f)
    out = np.zeros(len(p))
    for dx in (0, 1):
        for dy in (0, 1):
            for dz in (0, 1):
                c = (i0 + (dx, dy, dz)).astype(np.uint32)
                hsh = (
                    (c[:, 0] * np.uint32(73856093))
                    ^ (c[:, 1] * np.uint32(19349663))
                    ^ (c[:, 2] * np.uint32(83492791))
                )
                hsh = (hsh ^ np.uint32(seed & 0xFFFFFFFF)) * np.uint32(2654435761)
                v = (hsh >> np.uint32(16)).astype(np.float64) / 65535.0
                w = (
                    (f[:, 0] if dx else 1 - f[:, 0])
                    * (f[:, 1] if dy else 1 - f[:, 1])
                    * (f[:, 2] if dz else 1 - f[:, 2])
                )
                out += w * v
    return out


def _line(d: np.ndarray, width: float) -> np.ndarray:
    """1 on a line of half-width ``width`` around d = 0, smooth falloff to 0."""
    return np.clip(1.5 - np.abs(d) / width, 0.0, 1.0)


@dataclasses.dataclass
class _Anatomy:
    """Rest-pose landmarks the painter needs (world frame, metres)."""

    heads: dict[str, np.ndarray]
    eye_margin: dict[str, np.ndarray]
    eye_centre: dict[str, np.ndarray]
    eye_forward: dict[str, np.ndarray]
    lip_margin: np.ndarray
    palm_dir: dict[str, np.ndarray]
    tip: dict[str, np.ndarray]


def face_segments(model) -> np.ndarray:
    """Anny segment label per face [F] (index into ``anny_backend.SEGMENT_LABELS``; a face with
    none gets 0, one with several the last)."""
    labels = np.zeros(model.faces.shape[0], np.int64)
    for i, mask in enumerate(face_segment_masks(model.anny).T):
        labels[mask] = i
    return labels


def _anatomy(
    model,
    rest: np.ndarray,
    joints: np.ndarray,
    keypoints: np.ndarray,
    face_label: np.ndarray,
    palm_dir: dict[str, np.ndarray],
) -> _Anatomy:

    lab = {n: i for i, n in enumerate(SEGMENT_LABELS)}
    faces = model.faces.cpu().numpy()
    heads = {n: joints[i] for i, n in enumerate(model.joint_names)}

    def verts(*labels: str) -> np.ndarray:
        return np.unique(faces[np.isin(face_label, [lab[x] for x in labels])])

    def boundary(a: str, b: str) -> np.ndarray:
        return rest[np.intersect1d(verts(a), verts(b))]

    kp = {n: keypoints[i] for i, n in enumerate(model.keypoint_names)}
    eye_margin, eye_centre, eye_forward, tip = {}, {}, {}, {}
    for s, side in (("L", "left"), ("R", "right")):
        eye_margin[s] = boundary("head", f"eye_cavity.{s}")
        ball = rest[verts(f"eye_front.{s}", f"eye_back.{s}")]
        eye_centre[s] = ball.mean(axis=0)
        fwd = kp[f"face_{side}_iris"] - eye_centre[s]
        eye_forward[s] = fwd / np.linalg.norm(fwd)
        for i, finger in enumerate(("thumb", "index_finger", "middle_finger", "ring_finger", "pinky"), 1):
            tip[f"{i}.{s}"] = kp[f"{side}_hand_{finger}_tip"]
    return _Anatomy(
        heads, eye_margin, eye_centre, eye_forward, boundary("head", "mouth_cavity"), palm_dir, tip
    )


def _dist_to(points: np.ndarray, targets: np.ndarray) -> np.ndarray:
    from scipy.spatial import cKDTree

    return cKDTree(targets).query(points)[0]


def paint(
    p: np.ndarray,
    normal: np.ndarray,
    label: np.ndarray,
    bone: np.ndarray,
    model,
    anatomy: _Anatomy,
    look: Look,
    seed: int,
) -> np.ndarray:
    """Albedo and gloss [N, 4] (RGB, highlight strength) at surface points p [N, 3] (rest pose)
    with normals [N, 3], Anny segment label [N] and dominant bone index [N] (into
    ``model.joint_names``). Each region is painted on its own subset of points (the atlas has
    millions of texels)."""
    lab = {n: i for i, n in enumerate(SEGMENT_LABELS)}
    names = model.joint_names
    col = np.tile(np.asarray(look.skin), (len(p), 1))
    gloss = np.full(len(p), GLOSS["skin"])

    skin = np.isin(label, [lab["body"], lab["head"], lab["hand.L"], lab["hand.R"]])
    idx = np.nonzero(skin)[0]
    # Broad blotches and fine (3 mm) mottling: skin a blur cannot fake.
    fine = _hash_noise(p[idx], 0.003, seed + 9) - 0.5
    mottle = 0.94 + 0.09 * _hash_noise(p[idx], 0.02, seed) + 0.06 * fine
    col[idx] *= mottle[:, None]
    body = np.nonzero(label == lab["body"])[0]
    col[body], gloss[body] = _paint_body(
        p[body], normal[body], bone[body], names, anatomy, look, seed, col[body]
    )
    feet = np.nonzero(np.isin(label, [lab["foot.L"], lab["foot.R"]]))[0]
    if len(feet):
        fc = np.tile(np.asarray(look.shoes), (len(feet), 1))
        fc[p[feet, 1] < p[feet, 1].min() + 0.008] = (0.55, 0.55, 0.53)  # soles
        col[feet], gloss[feet] = fc, GLOSS["shoes"]
    for s in "LR":
        hand = np.nonzero(label == lab[f"hand.{s}"])[0]
        col[hand], gloss[hand] = _paint_hand(
            p[hand], normal[hand], bone[hand], names, anatomy, s, look, col[hand]
        )
    head = np.nonzero(label == lab["head"])[0]
    col[head], gloss[head] = _paint_head(p[head], anatomy, look, seed, col[head])
    for s in "LR":
        ball = np.nonzero(label == lab[f"eye_front.{s}"])[0]
        col[ball], gloss[ball] = _paint_eye(p[ball], anatomy, s, look, seed), GLOSS["eye"]
        col[label == lab[f"eye_back.{s}"]] = (0.9, 0.9, 0.88)
        col[label == lab[f"eye_cavity.{s}"]] = (0.15, 0.08, 0.07)
    mouth = np.isin(label, [lab["mouth_cavity"], lab["tongue"]])
    col[label == lab["mouth_cavity"]] = (0.35, 0.08, 0.08)
    col[label == lab["tongue"]] = (0.78, 0.42, 0.42)
    gloss[mouth] = GLOSS["mouth"]
    return np.concatenate([np.clip(col, 0.0, 1.0), gloss[:, None]], axis=1)


def _bone_table(names, pred) -> np.ndarray:
    return np.array([bool(pred(x)) for x in names])


def _paint_body(
    p, normal, bone, names, a: _Anatomy, look: Look, seed: int, col: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Shirt with sleeves and a printed chest panel, trousers below the waist, skin elsewhere
    (neck, forearms). Returns colour [N, 3] and gloss [N]."""
    h = a.heads
    lower = _bone_table(names, lambda x: x.startswith(("pelvis", "upperleg", "lowerleg", "foot", "toe")))[
        bone
    ]
    trousers = lower | (p[:, 1] < h["root"][1] + 0.09)
    scoop = np.exp(-((p[:, 0] / 0.07) ** 2)) * (p[:, 2] > h["neck01"][2])
    neck_y = h["neck01"][1] - 0.025 - 0.035 * scoop
    shirt = ~trousers & (p[:, 1] < neck_y)
    for s in "LR":
        elbow, wrist = h[f"lowerarm01.{s}"], h[f"wrist.{s}"]
        fore = wrist - elbow
        t = (p - elbow) @ fore / (fore @ fore)
        on_fore = _bone_table(names, lambda x, s=s: x.startswith(("lowerarm", "wrist")) and x.endswith(s))[
            bone
        ]
        shirt &= ~(on_fore & (t > 0.72))
    col = col.copy()
    q = p[shirt]
    # A checked shirt: two sets of fine stripes on the rest-pose surface, a diagonal overcheck,
    # a fine weave, and a light hem at the neckline.
    u = np.sin(2 * np.pi * q[:, 0] / 0.018)
    v = np.sin(2 * np.pi * q[:, 1] / 0.018)
    over = _line(np.mod(q[:, 0] + q[:, 2], 0.054) - 0.027, 0.0012)
    check = 0.75 + 0.12 * (u > 0.6) + 0.12 * (v > 0.6) + 0.25 * over
    weave = 0.95 + 0.05 * np.sin(2 * np.pi * (q[:, 0] - q[:, 1]) / 0.003)
    hem = 0.25 * _line(q[:, 1] - neck_y[shirt] + 0.006, 0.002)
    col[shirt] = np.asarray(look.shirt)[None] * (check * weave)[:, None] + hem[:, None]
    gloss = np.full(len(p), GLOSS["skin"])
    gloss[shirt] = GLOSS["shirt"]
    # A printed panel on the chest: a frame and blocky "lettering" with sharp 4 mm edges.
    chest_y = h["neck01"][1] - 0.14
    front = shirt & (normal[:, 2] > 0.5) & (p[:, 2] > h["spine01"][2])
    px, py = p[:, 0] / 0.085, (p[:, 1] - chest_y) / 0.07
    panel = front & (np.abs(px) < 1.0) & (np.abs(py) < 1.0)
    border = panel & ((np.abs(px) > 0.9) | (np.abs(py) > 0.86))
    cells = np.floor(p[:, :2] / 0.004).astype(np.int64)
    glyph = _hash_noise(np.concatenate([cells * 0.004, np.zeros((len(p), 1))], 1), 0.004, seed + 11) > 0.55
    rows = np.abs(np.mod(py + 1.0, 0.5) - 0.25) < 0.16  # three lines of "text"
    ink = border | (panel & (np.abs(px) < 0.8) & (np.abs(py) < 0.75) & rows & glyph)
    grain = 0.93 + 0.07 * _hash_noise(p[ink], 0.002, seed + 12)
    col[ink] = np.asarray(look.print_ink)[None] * grain[:, None]
    gloss[ink] = GLOSS["print"]
    q = p[trousers]
    twill = 0.88 + 0.12 * np.sin(2 * np.pi * (q[:, 1] + 0.6 * q[:, 0] + 0.6 * q[:, 2]) / 0.004)
    col[trousers] = (
        np.asarray(look.trousers)[None] * (twill * (0.9 + 0.2 * _hash_noise(q, 0.03, seed + 2)))[:, None]
    )
    gloss[trousers] = GLOSS["trousers"]
    return col, gloss


def _paint_hand(
    p, normal, bone, names, a: _Anatomy, s: str, look: Look, col: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """A tint per finger, creases across every finger joint, nails, palm lines. Returns colour
    [N, 3] and gloss [N]."""
    h = a.heads
    col = col.copy()
    gloss = np.full(len(p), GLOSS["skin"])
    for i in range(1, 6):
        finger = _bone_table(names, lambda x, i=i: x in {f"finger{i}-{k}.{s}" for k in (1, 2, 3)})[bone]
        q = p[finger]
        fc = col[finger] * np.asarray(FINGER_TINTS[i - 1])
        crease = np.zeros(len(q))
        for k in (2, 3):
            j0, j1 = h[f"finger{i}-{k - 1}.{s}"], h[f"finger{i}-{k}.{s}"]
            d = (j1 - j0) / np.linalg.norm(j1 - j0)
            along = (q - j1) @ d
            radial = np.linalg.norm((q - j1) - along[:, None] * d, axis=1)
            crease = np.maximum(crease, _line(along, 0.0009) * (radial < 0.02))
            crease = np.maximum(crease, 0.6 * _line(along - 0.003, 0.0006) * (radial < 0.02))
        fc *= (1.0 - 0.45 * crease)[:, None]
        # The nail: the back of the distal phalanx towards the tip.
        head, tip = h[f"finger{i}-3.{s}"], a.tip[f"{i}.{s}"]
        d = tip - head
        t = (q - head) @ d / (d @ d)
        distal = _bone_table(names, lambda x, i=i: x == f"finger{i}-3.{s}")[bone[finger]]
        nail = distal & (t > 0.4) & (normal[finger] @ (-a.palm_dir[s]) > 0.45)
        nc = np.tile(np.asarray(look.nails), (len(q), 1))
        nc[t > 0.93] = (0.97, 0.95, 0.92)  # the free edge
        nc[t < 0.47] = (0.85, 0.62, 0.60)  # cuticle
        fc[nail] = nc[nail]
        col[finger] = fc
        fg = gloss[finger]
        fg[nail] = GLOSS["nail"]
        gloss[finger] = fg
    palm = (normal @ a.palm_dir[s] > 0.5) & _bone_table(names, lambda x: x == f"wrist.{s}")[bone]
    q = p[palm] - h[f"wrist.{s}"]
    lines = _line(np.sin(2 * np.pi * (q @ np.array([0.3, 1.0, 0.2])) / 0.02), 0.08)
    col[palm] *= (1.0 - 0.25 * lines)[:, None]
    return col, gloss


def _paint_head(p, a: _Anatomy, look: Look, seed: int, col: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Hair, eyebrows, lid lines and lips. Returns colour [N, 3] and gloss [N]."""
    h = a.heads
    col = col.copy()
    gloss = np.full(len(p), GLOSS["skin"])
    hair = (p[:, 1] - h["head"][1]) + 0.75 * (0.04 - p[:, 2]) > 0.055
    q = p[hair]
    strands = 0.8 + 0.2 * np.sin(2 * np.pi * (q[:, 0] * 0.9 + q[:, 2] * 0.4) / 0.0025) * _hash_noise(
        q, 0.01, seed + 3
    )
    col[hair] = np.asarray(look.hair)[None] * strands[:, None]
    gloss[hair] = GLOSS["hair"]
    dark = np.asarray(look.hair) * 0.6
    for s in "LR":
        margin = a.eye_margin[s]
        ec = margin.mean(axis=0)
        half = 0.5 * (margin[:, 0].max() - margin[:, 0].min())
        dx = (p[:, 0] - ec[0]) / (1.25 * half)
        front = p[:, 2] > ec[2] - 0.025
        brow_y = ec[1] + 0.020 + 0.008 * (1.0 - dx**2) - 0.003 * (np.sign(ec[0]) * dx)
        brow = front & (np.abs(dx) < 1.0) & (np.abs(p[:, 1] - brow_y) < 0.0032 * (1.15 - 0.5 * np.abs(dx)))
        col[brow] = dark[None] * (0.8 + 0.4 * _hash_noise(p[brow], 0.0015, seed + 4))[:, None]
        near = front & (np.abs(p[:, 0] - ec[0]) < 2 * half) & (np.abs(p[:, 1] - ec[1]) < 0.02)
        if near.any():
            d = _dist_to(p[near], margin)
            upper = p[near, 1] > ec[1] - 0.001
            liner = np.clip(1.0 - d / np.where(upper, 0.0016, 0.0008), 0, 1)
            col[near] *= (1.0 - 0.75 * liner)[:, None]
    lips = a.lip_margin
    mc = lips.mean(axis=0)
    half_w = 0.5 * (lips[:, 0].max() - lips[:, 0].min())
    near = (
        (np.abs(p[:, 0] - mc[0]) < 1.3 * half_w) & (np.abs(p[:, 1] - mc[1]) < 0.03) & (p[:, 2] > mc[2] - 0.03)
    )
    if near.any():
        q = p[near]
        d = _dist_to(q, lips)
        taper = np.clip(1.15 - (np.abs(q[:, 0] - mc[0]) / (1.1 * half_w)) ** 2, 0, 1)
        width = np.where(q[:, 1] < mc[1], 0.0085, 0.0065) * taper
        lip = np.clip((width - d) / 0.0012, 0.0, 1.0)[:, None]
        lc = np.asarray(look.lips)[None] * (0.92 + 0.08 * np.sin(2 * np.pi * q[:, 0] / 0.002))[:, None]
        c = col[near] * (1 - lip) + lc * lip
        col[near] = c * (1.0 - 0.5 * _line(d, 0.0007))[:, None]  # the line between the lips
        gloss[near] = GLOSS["skin"] + (GLOSS["lips"] - GLOSS["skin"]) * lip[:, 0]
    return col, gloss


def _paint_eye(p, a: _Anatomy, s: str, look: Look, seed: int) -> np.ndarray:
    """Sclera, iris with streaks and a limbal ring, pupil, a highlight."""
    r = p - a.eye_centre[s]
    cosang = (r @ a.eye_forward[s]) / np.maximum(np.linalg.norm(r, axis=1), 1e-9)
    ang = np.arccos(np.clip(cosang, -1, 1))
    eye = np.tile(np.array([0.93, 0.92, 0.90]), (len(p), 1))
    iris = ang < 0.42
    streak = 0.85 + 0.3 * _hash_noise(p[iris], 0.0008, seed + 5)
    eye[iris] = np.asarray(look.iris)[None] * streak[:, None]
    eye[(ang > 0.37) & (ang < 0.42)] *= 0.55  # limbal ring
    eye[ang < 0.17] = (0.03, 0.03, 0.03)
    eye[(ang > 0.06) & (ang < 0.09) & (r[:, 1] > 0)] = (0.9, 0.9, 0.9)  # highlight
    return eye


def bake_texture(
    model, params, look: Look, renderer, size: int, seed: int = 0, face_label: np.ndarray | None = None
) -> np.ndarray:
    """Paint the subject of ``params`` (batch 1; its shape sets the rest pose) into a
    ``size x size`` texture for ``renderer.set_surface(texture=..., uv=..., face_uv=...)`` with
    Anny's UV atlas. ``face_label``: :func:`face_segments` if already computed. Returns uint8
    [size, size, 4]: albedo and gloss."""
    from scipy import ndimage

    with torch.no_grad():
        rest_params = model.default_params(1)
        rest_params.shape = params.shape[:1].to(rest_params.shape)
        out = model(rest_params)
        kp = model.keypoints(out)[0].double().numpy()
    rest = out.vertices[0].double().numpy()
    joints = out.joints[0].double().numpy()
    faces = model.faces.cpu().numpy()
    face_label = face_segments(model) if face_label is None else face_label
    anatomy = _anatomy(model, rest, joints, kp, face_label, rest_axes(model, params.shape).palm)
    uv = model.anny.texture_coordinates.cpu().numpy()
    fuv = model.anny.face_texture_coordinate_indices.cpu().numpy()
    pos, fid = renderer.bake(uv, fuv, rest, size)
    nrm, _ = renderer.bake(uv, fuv, vertex_normals(rest, faces), size)
    valid = fid >= 0
    f = fid[valid]
    face_bone = model.skinning_weights.cpu().numpy()[faces].sum(axis=1).argmax(axis=1)
    normal = nrm[valid].astype(np.float64)
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-9)
    albedo = paint(
        pos[valid].astype(np.float64), normal, face_label[f], face_bone[f], model, anatomy, look, seed
    )
    tex = np.zeros((size, size, 4))
    tex[valid] = albedo
    # Fill texels outside the UV islands with the nearest painted texel, so mipmaps and
    # bilinear filtering at seams do not bleed black.
    _, (iy, ix) = ndimage.distance_transform_edt(~valid, return_indices=True)
    tex = tex[iy, ix]
    return np.clip(np.round(tex * 255.0), 0, 255).astype(np.uint8)


def apply_look(
    renderer, model, params, look: Look, size: int, seed: int = 0, face_label: np.ndarray | None = None
) -> None:
    """Paint the subject (:func:`bake_texture`, same arguments) and put the texture on ``renderer``
    (a ``MeshRenderer`` of ``model.faces``) through Anny's UV atlas."""
    texture = bake_texture(model, params, look, renderer, size, seed=seed, face_label=face_label)
    renderer.set_surface(
        texture=texture,
        uv=model.anny.texture_coordinates.cpu().numpy(),
        face_uv=model.anny.face_texture_coordinate_indices.cpu().numpy(),
    )
