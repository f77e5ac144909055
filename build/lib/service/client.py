"""``EvaClient``: the REST API from Python, typed by the API's own schemas (``service.schemas``,
``service.animation_schemas``): what ``eva demo`` speaks, and what a script driving the service
would.

    with EvaClient("http://127.0.0.1:8000", api_key=key) as api:
        created = api.create_avatar(Path("me.mp4"), {"preset": "fast"})
        api.wait(created.job_id, on_update=lambda job: print(job.stage, job.progress))
        png = api.render(created.avatar_id, {"pose": {"joints": {"upperarm01.L": [0, 0, -1.0]}}})

An answer of 400 or more raises ``ApiError`` with the status and the API's reason; a job that
ends failed or cancelled raises ``JobFailed`` from ``wait``.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from pathlib import Path

import httpx
from pydantic import BaseModel

from service.animation_schemas import AnimationCreated, AnimationInfo
from service.schemas import AvatarCreated, AvatarInfo, Health, JobInfo


class ApiError(RuntimeError):
    """The API answered ``status`` >= 400; ``detail``: its reason."""

    def __init__(self, what: str, status: int, detail: str) -> None:
        super().__init__(f"{what} failed: HTTP {status} {detail}")
        self.status, self.detail = status, detail


class JobFailed(RuntimeError):
    """A job ended failed or cancelled (``job``: its last state, ``job.error`` the reason)."""

    def __init__(self, job: JobInfo) -> None:
        super().__init__(f"the {job.kind} job {job.state}: {job.error}")
        self.job = job


def form_fields(options: Mapping[str, object] | BaseModel | None) -> dict[str, str]:
    """Upload form fields from a dict or a form model (its set fields): JSON's spelling of
    booleans, everything else as text."""
    if isinstance(options, BaseModel):
        options = options.model_dump(mode="json", exclude_unset=True)
    fields = {}
    for name, value in (options or {}).items():
        fields[name] = ("true" if value else "false") if isinstance(value, bool) else str(value)
    return fields


class EvaClient:
    """base_url: the API (``LocalStack.base_url``, ``http://host:8000``); api_key: sent as
    ``X-API-Key``; http: an ``httpx.Client`` to use instead (e.g. FastAPI's ``TestClient``)."""

    def __init__(
        self,
        base_url: str = "http://127.0.0.1:8000",
        api_key: str | None = None,
        timeout: float = 120.0,
        http: httpx.Client | None = None,
    ) -> None:
        headers = {"X-API-Key": api_key} if api_key else {}
        self.http = http or httpx.Client(base_url=base_url, timeout=timeout)
        self.http.headers.update(headers)

    def close(self) -> None:
        self.http.close()

    def __enter__(self) -> EvaClient:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _call(self, what: str, method: str, url: str, **kwargs) -> httpx.Response:
        response = self.http.request(method, url, **kwargs)
        if response.status_code >= 400:
            try:
                detail = str(response.json().get("detail"))
            except ValueError:
                detail = response.text[:300]
            raise ApiError(what, response.status_code, detail)
        return response

    def _upload(self, what: str, url: str, video: Path, options) -> dict:
        """POST ``video`` as the form's ``video`` file with ``options`` as its fields: the JSON answer."""
        with Path(video).open("rb") as f:
            files = {"video": (Path(video).name, f, "video/mp4")}
            return self._call(what, "POST", url, files=files, data=form_fields(options)).json()

    # -- the service -------------------------------------------------------------------------------
    def health(self) -> Health:
        return Health.model_validate(self._call("health", "GET", "/healthz").json())

    # -- avatars -----------------------------------------------------------------------------------
    def create_avatar(
        self, video: Path, options: Mapping[str, object] | BaseModel | None = None
    ) -> AvatarCreated:
        """Upload ``video`` with the form's ``options`` (``AvatarForm``'s fields): a queued job."""
        return AvatarCreated.model_validate(self._upload("upload", "/avatars", video, options))

    def avatar(self, avatar_id: str) -> AvatarInfo:
        return AvatarInfo.model_validate(self._call("avatar info", "GET", f"/avatars/{avatar_id}").json())

    def render(self, avatar_id: str, request: Mapping[str, object] | BaseModel | None = None) -> bytes:
        """The image (PNG, or JPEG with ``format``) of a ``RenderRequest``: pose, camera, size."""
        body = (
            request.model_dump(mode="json", exclude_unset=True)
            if isinstance(request, BaseModel)
            else dict(request or {})
        )
        return self._call("render", "POST", f"/avatars/{avatar_id}/render", json=body).content

    # -- animations --------------------------------------------------------------------------------
    def create_animation(
        self, avatar_id: str, video: Path, options: Mapping[str, object] | BaseModel | None = None
    ) -> AnimationCreated:
        """The avatar performing ``video`` (``AnimationForm``'s fields in ``options``): a queued job."""
        url = f"/avatars/{avatar_id}/animations"
        return AnimationCreated.model_validate(self._upload("animation upload", url, video, options))

    def animation(self, animation_id: str) -> AnimationInfo:
        url = f"/animations/{animation_id}"
        return AnimationInfo.model_validate(self._call("animation info", "GET", url).json())

    def animation_video(self, animation_id: str) -> bytes:
        return self._call("animation", "GET", f"/animations/{animation_id}/video").content

    # -- jobs --------------------------------------------------------------------------------------
    def job(self, job_id: str) -> JobInfo:
        return JobInfo.model_validate(self._call("job status", "GET", f"/jobs/{job_id}").json())

    def wait(
        self,
        job_id: str,
        timeout: float = 3600.0,
        every: float = 0.5,
        on_update: Callable[[JobInfo], None] | None = None,
        alive: Callable[[], bool] | None = None,
    ) -> JobInfo:
        """Poll the job until it succeeds (returned); ``JobFailed`` when it fails or is cancelled,
        ``TimeoutError`` after ``timeout`` seconds or as soon as ``alive()`` (e.g.
        ``LocalStack.alive``) says the service is gone. ``on_update`` sees every poll."""
        deadline = time.monotonic() + timeout
        while True:
            job = self.job(job_id)
            if on_update is not None:
                on_update(job)
            if job.state == "succeeded":
                return job
            if job.state in ("failed", "cancelled"):
                raise JobFailed(job)
            if time.monotonic() > deadline or (alive is not None and not alive()):
                raise TimeoutError(
                    f"the {job.kind} job {job_id} did not finish (last: {job.state}, {job.stage})"
                )
            time.sleep(every)
