"""``ServiceSettings``: the API's configuration (limits, binding, key) around a ``JobsConfig``."""

from __future__ import annotations

import os

from pydantic import BaseModel, ConfigDict, Field

from jobs.config import JobsConfig


class ServiceSettings(BaseModel):
    """host / port: where ``eva serve`` binds (loopback by default); api_key: when set, every
    endpoint but ``/healthz`` needs the header ``X-API-Key``; max_upload_mb, max_video_seconds:
    limits on an uploaded video; max_render_pixels: largest ``width`` or ``height`` of a render;
    avatar_cache: avatars kept loaded for rendering; preload_body_models: loaded in the background
    at start-up so the first render does not wait for them."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    jobs: JobsConfig
    host: str = "127.0.0.1"
    port: int = Field(8000, ge=1, le=65535)
    api_key: str | None = None
    max_upload_mb: float = Field(512.0, gt=0)
    max_video_seconds: float = Field(600.0, gt=0)
    max_render_pixels: int = Field(2048, ge=16)
    avatar_cache: int = Field(4, ge=1)
    preload_body_models: tuple[str, ...] = ("anny",)

    @property
    def max_upload_bytes(self) -> int:
        return int(self.max_upload_mb * 1024 * 1024)

    @classmethod
    def from_env(cls, jobs: JobsConfig | None = None, **overrides) -> ServiceSettings:
        """From ``EVA_HOST``, ``EVA_PORT``, ``EVA_API_KEY``, ``EVA_MAX_UPLOAD_MB``,
        ``EVA_MAX_VIDEO_SECONDS``, ``EVA_MAX_RENDER_PIXELS`` (and ``JobsConfig.from_env``);
        ``overrides`` that are not None win."""
        names = {"host": "EVA_HOST", "port": "EVA_PORT", "api_key": "EVA_API_KEY",
                 "max_upload_mb": "EVA_MAX_UPLOAD_MB", "max_video_seconds": "EVA_MAX_VIDEO_SECONDS",
                 "max_render_pixels": "EVA_MAX_RENDER_PIXELS"}  # fmt: skip
        values = {k: os.environ[v] for k, v in names.items() if os.environ.get(v)}
        values.update({k: v for k, v in overrides.items() if v is not None})
        return cls(jobs=jobs or JobsConfig.from_env(), **values)
