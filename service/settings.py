"""``ServiceSettings``: the API's configuration (binding, key, limits) around a ``JobsConfig``."""

from __future__ import annotations

import ipaddress
from pathlib import Path
from typing import Annotated

from pydantic import Field, field_validator, model_validator
from pydantic.fields import FieldInfo
from pydantic_settings import BaseSettings, NoDecode, SettingsConfigDict

from jobs.config import ENV_PREFIX, JobsConfig
from service.accounts import MIN_KEY_LENGTH, Account, read_accounts
from service.connections import ConnectionLimits

LOOPBACK_NAMES = ("127.0.0.1", "localhost", "::1", "[::1]")


def env_name(name: str, field: FieldInfo, prefix: str = ENV_PREFIX) -> str:
    """The environment variable of a settings field: its alias, else the prefix and its name."""
    return field.validation_alias if isinstance(field.validation_alias, str) else prefix + name.upper()


def is_loopback(host: str) -> bool:
    if host in ("localhost", "[::1]"):
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def _comma_list(value):
    """``"a, b"`` (an environment variable) -> ``("a", "b")``; anything else as it is."""
    if isinstance(value, str):
        return tuple(part.strip() for part in value.split(",") if part.strip())
    return value


class ServiceSettings(BaseSettings):
    """host / port: where ``eva serve`` binds (loopback by default; any other address needs an
    ``api_key`` or ``accounts``); api_key: when set, every endpoint but ``/healthz`` (the docs
    included) needs the header ``X-API-Key``; accounts: several keys, each with its owner, who
    sees only their own avatars, animations and jobs (``service.accounts``; instead of
    ``api_key``); allowed_hosts: accepted ``Host`` headers (default: the loopback names
    without a key, any with one; DNS rebinding cannot supply the key).

    Limits, all enforced before a request reaches its endpoint: max_upload_mb, the body of an
    upload (a video for an avatar, a driving video or poses for an animation); max_json_kb, every
    other body; max_uploads, uploads of either kind at once; body_min_kb_s, the slowest average
    rate a body may arrive at once body_grace_s have passed (else 408); body_timeout_s, longest
    pause while a body streams in (a slow sender is cut off with 408); max_requests, requests in
    flight (past it, the answer is 503 with ``Retry-After``; ``/healthz`` always passes);
    connections, the connections that have not sent a request's headers (``ConnectionLimits``:
    closed after a timeout, the oldest first past a cap).

    Videos: max_video_seconds; probe_timeout_s / probe_memory_mb, the child process that reads an
    upload's headers; max_poses_mb, a JSON pose sequence uploaded for an animation (parsed in the
    API). Jobs: max_queued_jobs, quota of jobs (of either kind) waiting for a worker (per owner
    with accounts).

    Renders: max_render_side, largest width or height; max_render_pixels, width x height;
    max_renders at once, up to render_queue more waiting at most render_wait_s; avatar_cache:
    avatars kept loaded; preload_body_models: loaded in the background at start-up so the first
    render does not wait for them.

    Every field can be set from the environment as ``EVA_<FIELD>`` (``EVA_HOST``,
    ``EVA_MAX_RENDERS``, ...; empty values are ignored; lists comma-separated; ``connections``'
    fields as ``EVA_CONNECTIONS__HEADER_TIMEOUT_S``), and ``jobs`` from ``JobsConfig``'s own
    variables; ``accounts`` is read from the keys file that ``EVA_API_KEYS_FILE`` names.
    Arguments given to the constructor win over the environment (``docs/configuration.md``)."""

    model_config = SettingsConfigDict(
        env_prefix=ENV_PREFIX,
        env_nested_delimiter="__",
        env_ignore_empty=True,
        extra="forbid",
        frozen=True,
        populate_by_name=True,
    )

    jobs: JobsConfig = Field(default_factory=JobsConfig)
    host: str = "127.0.0.1"
    port: int = Field(8000, ge=1, le=65535)
    api_key: str | None = None
    accounts: Annotated[tuple[Account, ...], NoDecode] = Field((), validation_alias="EVA_API_KEYS_FILE")
    allowed_hosts: Annotated[tuple[str, ...] | None, NoDecode] = None
    max_upload_mb: float = Field(512.0, gt=0)
    max_json_kb: float = Field(64.0, gt=0)
    max_uploads: int = Field(2, ge=1)
    body_timeout_s: float = Field(30.0, gt=0)
    body_min_kb_s: float = Field(16.0, gt=0)
    body_grace_s: float = Field(10.0, ge=0)
    max_requests: int = Field(64, ge=1)
    connections: ConnectionLimits = ConnectionLimits()
    max_video_seconds: float = Field(600.0, gt=0)
    probe_timeout_s: float = Field(30.0, gt=0)
    probe_memory_mb: int = Field(1024, ge=128)
    max_poses_mb: float = Field(16.0, gt=0)
    max_queued_jobs: int = Field(32, ge=1)
    max_render_side: int = Field(4096, ge=16, le=4096)
    max_render_pixels: int = Field(2048 * 2048, ge=16 * 16)
    # One render at a time: a render's torch ops already use every core, and two at once made 16
    # clients' throughput 0.72-0.99x one client's, against 0.87-1.11x (docs/speed.md).
    max_renders: int = Field(1, ge=1)
    render_queue: int = Field(16, ge=0)
    render_wait_s: float = Field(10.0, gt=0)
    avatar_cache: int = Field(4, ge=1)
    preload_body_models: Annotated[tuple[str, ...], NoDecode] = ("anny",)

    @field_validator("allowed_hosts", "preload_body_models", mode="before")
    @classmethod
    def _lists(cls, value):
        return _comma_list(value)

    @field_validator("accounts", mode="before")
    @classmethod
    def _keys_file(cls, value):
        return read_accounts(value) if isinstance(value, str | Path) else value

    @field_validator("api_key")
    @classmethod
    def _long_enough(cls, key: str | None) -> str | None:
        if key is not None and len(key) < MIN_KEY_LENGTH:
            raise ValueError(
                f"the API key has {len(key)} characters; at least {MIN_KEY_LENGTH} are needed "
                "(`openssl rand -hex 24` makes one)"
            )
        return key

    @model_validator(mode="after")
    def _one_way_of_keys(self) -> ServiceSettings:
        if self.api_key is not None and self.accounts:
            raise ValueError("give one API key (EVA_API_KEY) or a keys file (EVA_API_KEYS_FILE), not both")
        return self

    @property
    def keyed(self) -> bool:
        """Whether requests need a key (one key, or the accounts' keys)."""
        return self.api_key is not None or bool(self.accounts)

    @model_validator(mode="after")
    def _no_open_api_on_a_network(self) -> ServiceSettings:
        if not self.keyed and not is_loopback(self.host):
            raise ValueError(
                f"refusing to serve on {self.host} without an API key: anyone who can reach it could "
                "upload, export and delete avatars; set EVA_API_KEY (or --api-key-file), or bind 127.0.0.1"
            )
        return self

    @property
    def max_upload_bytes(self) -> int:
        return int(self.max_upload_mb * 1024 * 1024)

    @property
    def max_poses_bytes(self) -> int:
        return int(min(self.max_poses_mb, self.max_upload_mb) * 1024 * 1024)

    @property
    def max_json_bytes(self) -> int:
        return int(self.max_json_kb * 1024)

    @property
    def trusted_hosts(self) -> list[str]:
        if self.allowed_hosts is not None:
            return list(self.allowed_hosts)
        if self.keyed:
            return ["*"]
        extra = [] if self.host in ("0.0.0.0", "::") else [self.host]
        return [*LOOPBACK_NAMES, *extra]

    @classmethod
    def from_env(cls, jobs: JobsConfig | None = None, **overrides) -> ServiceSettings:
        """The environment's settings (class docstring), with ``jobs`` and the ``overrides`` that
        are not None."""
        given = {k: v for k, v in {"jobs": jobs, **overrides}.items() if v is not None}
        return cls(**given)
