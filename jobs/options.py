"""``JobOptions``: what a user can choose for one avatar job (the form fields of ``POST /avatars``)."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from eva_engine.recipes import METHODS, PRESETS

Preset = Literal[*PRESETS]
Method = Literal[*METHODS]
# Bounds of what one job may ask for (with JobsConfig's frame budget and Gaussian cap, they bound
# its memory and time): the paper trains 2,000 iterations, 3DGS 30,000 on a GPU.
MAX_FRAMES, MIN_SIZE, MAX_SIZE, MAX_ITERATIONS = 2000, 64, 2048, 20_000


class JobOptions(BaseModel):
    """preset: training preset (``eva_engine.recipes.PRESETS``: ``tiny`` for tests, ``fast``
    ~minutes on a laptop CPU, ``default`` the paper's 2,000 iterations); max_frames: frames of the
    video used (evenly from the start); max_size: longest image side the frames are resized to;
    body_model: ``anny`` (embedded) or ``smplx`` (needs the user's own model files); iterations /
    image_scale: override the preset's; fit_scale: scales the body-model alignment's L-BFGS
    iterations (1 = the paper's 60/40/60); method: the training method
    (``eva_engine.recipes.METHODS``: ``eva`` is the paper's full method, ``3dgs+body`` its
    baseline); None: the preset's own (3DGS density control with the full objective).
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    preset: Preset = "fast"
    max_frames: int = Field(120, ge=1, le=MAX_FRAMES)
    max_size: int = Field(512, ge=MIN_SIZE, le=MAX_SIZE)
    body_model: Literal["anny", "smplx"] = "anny"
    iterations: int | None = Field(None, ge=1, le=MAX_ITERATIONS)
    image_scale: float | None = Field(None, gt=0.05, le=1.0)
    fit_scale: float = Field(1.0, gt=0.0, le=4.0)
    method: Method | None = None

    def fit_config(self):
        """The alignment's ``FitConfig`` with ``fit_scale`` applied."""
        from eva_engine.align import scaled_fit_config

        return scaled_fit_config(self.fit_scale)
