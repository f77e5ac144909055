"""``JobOptions``: what a user can choose for one avatar job (the form fields of ``POST /avatars``)."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from eva_engine.recipes import METHODS, PRESETS, describe_methods, describe_presets

Preset = Literal[*PRESETS]
Method = Literal[*METHODS]
# Bounds of what one job may ask for (with JobsConfig's frame budget and Gaussian cap, they bound
# its memory and time): the paper trains 2,000 iterations, 3DGS 30,000 on a GPU.
MAX_FRAMES, MIN_SIZE, MAX_SIZE, MAX_ITERATIONS = 2000, 64, 2048, 20_000
# Fewer frames with a person than this and a job refuses the video: half are held out to score
# the avatar (``eval.held_out_every``), the rest are too few views of the person to train on.
MIN_FRAMES = 8


class JobOptions(BaseModel):
    """What a user chooses for one avatar job; the fields, defaults and bounds of the form of
    ``POST /avatars``."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    preset: Preset = Field("fast", description=f"Training preset: {describe_presets()}.")
    max_frames: int = Field(
        120, ge=MIN_FRAMES, le=MAX_FRAMES, description="Frames of the video used, evenly from the start."
    )
    max_size: int = Field(
        512, ge=MIN_SIZE, le=MAX_SIZE, description="Longest image side the frames are resized to (pixels)."
    )
    body_model: Literal["anny", "smplx"] = Field(
        "anny", description="anny (embedded) or smplx (needs the user's own model files)."
    )
    iterations: int | None = Field(None, ge=1, le=MAX_ITERATIONS, description="Overrides the preset's.")
    image_scale: float | None = Field(None, gt=0.05, le=1.0, description="Overrides the preset's.")
    fit_scale: float = Field(
        1.0, gt=0.0, le=4.0, description="Scales the body fit's L-BFGS iterations (1: the paper's)."
    )
    method: Method | None = Field(
        None,
        description=f"Training method: {describe_methods()}; none: the preset's own (3DGS density "
        "control with the full objective).",
    )
    face_closeups: bool = Field(
        False,
        description="Also train on close-ups of the face at the video's own resolution (a video "
        "larger than max_size), rasterized antialiased so the frame draws the face's fine Gaussians "
        "as the close-ups do: a sharper face, about 40% more training time.",
    )

    def fit_config(self):
        """The alignment's ``FitConfig`` with ``fit_scale`` applied."""
        from eva_engine.align import scaled_fit_config

        return scaled_fit_config(self.fit_scale)

    def preprocess_config(self, video_frames: int | None = None):
        """The ``PreprocessConfig`` of this job on a video of ``video_frames`` frames (None:
        unknown, taken as ``max_frames``): its frame and size bounds, the scaled fit, some frames
        kept out of training (``eval.held_out_every``) for the avatar's quality report, and the
        input checks with ``MIN_FRAMES``."""
        from eva_engine.align import InputChecks, PreprocessConfig
        from eva_engine.data.face_crops import FaceCropConfig
        from eva_engine.eval import held_out_every

        frames = min(video_frames or self.max_frames, self.max_frames)
        return PreprocessConfig(
            max_frames=self.max_frames,
            max_size=self.max_size,
            fitting=self.fit_config(),
            test_every=held_out_every(frames),
            checks=InputChecks(min_frames=MIN_FRAMES),
            face_crops=FaceCropConfig() if self.face_closeups else None,
        )

    def train_config(self, max_gaussians: int, max_std_m: float | None = None):
        """The ``TrainConfig`` of this job: its preset with the overrides and method it asks for,
        the service's cap on Gaussians (``max_gaussians``, whatever the preset or method: memory
        and render time) and its bound on their size (``max_std_m`` metres, every part: a
        Gaussian larger than that is a smear from any other view; None: the preset's)."""
        import dataclasses

        from eva_engine.train import preset, with_method
        from eva_engine.train.face_views import FaceViewConfig

        overrides: dict = {}
        if self.iterations is not None:
            overrides["iterations"] = self.iterations
        if self.image_scale is not None:
            overrides["image_scale"] = self.image_scale
        config = preset(self.preset, **overrides)
        if self.method is not None:
            config = with_method(config, self.method)
        if self.face_closeups:  # antialiased, Mip-Splatting's 2D filter: docs/novel-views.md
            avatar = dataclasses.replace(config.avatar, rasterize_mode="antialiased", eps2d=0.1)
            config = dataclasses.replace(config, face_view=FaceViewConfig(weight=1.0), avatar=avatar)
        cap = min(config.strategy.max_gaussians or max_gaussians, max_gaussians)
        config = dataclasses.replace(config, strategy=dataclasses.replace(config.strategy, max_gaussians=cap))
        if max_std_m is not None:
            own = config.avatar.max_scale or (max_std_m,) * 3
            bound = tuple(min(b, max_std_m) for b in own)
            config = dataclasses.replace(config, avatar=dataclasses.replace(config.avatar, max_scale=bound))
        return config
