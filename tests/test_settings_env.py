"""The settings of the queue (``JobsConfig``) and of the API (``ServiceSettings``) come from the
environment through pydantic-settings: every field as ``EVA_<FIELD>``, the two older names, lists
comma-separated, nested fields with ``__``, empty values ignored, constructor arguments first;
``docs/configuration.md`` is generated from the models and must match them."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from pydantic import ValidationError

from jobs.config import JobsConfig
from service.config_docs import configuration_markdown
from service.settings import ServiceSettings

ROOT = Path(__file__).resolve().parents[1]
KEY = "k" * 24


@pytest.fixture
def clean_env(monkeypatch):
    """No EVA_ variable but the engine's data folder (the suite's own environment may set some)."""
    import os

    for name in list(os.environ):
        if name.startswith("EVA_") and name != "EVA_DATA_DIR":
            monkeypatch.delenv(name)
    return monkeypatch


def test_every_jobs_field_reads_its_variable(clean_env, tmp_path):
    env = {
        "EVA_SERVICE_DIR": str(tmp_path),
        "EVA_QUEUE_URL": "redis://localhost:6379/0",
        "EVA_QUEUE_NAME": "other",
        "EVA_MAX_ATTEMPTS": "3",
        "EVA_MAX_WORKER_LOSSES": "7",
        "EVA_STALE_AFTER_S": "60",
        "EVA_HEARTBEAT_S": "2",
        "EVA_JOB_THREADS": "1",
        "EVA_RECORDS_URL": "redis://localhost:6379/1",
        "EVA_STORAGE_URL": "s3://bucket/prefix",
        "EVA_S3_ENDPOINT_URL": "http://127.0.0.1:9000",
        "EVA_JOB_MEMORY_MB": "2048",
        "EVA_JOB_TIMEOUT_S": "99",
        "EVA_MAX_FRAME_PIXELS": "100000",
        "EVA_MAX_VIDEO_SIDE": "1024",
        "EVA_MAX_GAUSSIANS": "5000",
        "EVA_MAX_GAUSSIAN_STD_M": "0.2",
        "EVA_REQUEUE_AFTER_S": "30",
        "EVA_ORPHAN_TTL_S": "40",
        "EVA_KEEP_RECORDS_DAYS": "3",
    }
    defaults = JobsConfig(data_dir=tmp_path / "other")
    for name, value in env.items():
        clean_env.setenv(name, value)
    config = JobsConfig()
    changed = {n for n in JobsConfig.model_fields if getattr(config, n) != getattr(defaults, n)}
    assert changed == set(JobsConfig.model_fields), "a field the environment does not reach"
    assert (config.data_dir, config.threads, config.max_gaussian_std_m) == (tmp_path, 1, 0.2)
    # Constructor arguments win; "0" is no memory limit; an empty value is ignored.
    clean_env.setenv("EVA_JOB_MEMORY_MB", "0")
    clean_env.setenv("EVA_S3_ENDPOINT_URL", "")
    config = JobsConfig(max_attempts=5)
    assert (config.max_attempts, config.job_memory_mb, config.s3_endpoint_url) == (5, None, None)
    clean_env.setenv("EVA_MAX_ATTEMPTS", "eleven")
    with pytest.raises(ValidationError, match="max_attempts"):
        JobsConfig()


def test_service_settings_read_lists_nested_fields_and_the_keys_file(clean_env, tmp_path):
    keys = tmp_path / "keys.json"
    keys.write_text(json.dumps({"accounts": [{"owner": "a", "key": KEY}]}))
    clean_env.setenv("EVA_SERVICE_DIR", str(tmp_path))
    clean_env.setenv("EVA_ALLOWED_HOSTS", "eva.example, api.example")
    clean_env.setenv("EVA_PRELOAD_BODY_MODELS", "")
    clean_env.setenv("EVA_CONNECTIONS__HEADER_TIMEOUT_S", "3.5")
    clean_env.setenv("EVA_API_KEYS_FILE", str(keys))
    clean_env.setenv("EVA_MAX_RENDERS", "3")
    settings = ServiceSettings()
    assert settings.jobs.data_dir == tmp_path
    assert settings.allowed_hosts == ("eva.example", "api.example")
    assert settings.preload_body_models == ("anny",)  # empty: ignored
    assert settings.connections.header_timeout_s == 3.5
    assert [a.owner for a in settings.accounts] == ["a"] and settings.max_renders == 3
    # None overrides keep the environment's value; the others win.
    assert ServiceSettings.from_env(max_renders=None, port=9000).max_renders == 3
    assert ServiceSettings.from_env(port=9000).port == 9000
    clean_env.setenv("EVA_API_KEY", KEY)  # a key and a keys file: refused, saying which variables
    with pytest.raises(ValidationError, match="EVA_API_KEY"):
        ServiceSettings()
    clean_env.delenv("EVA_API_KEY")
    clean_env.setenv("EVA_API_KEYS_FILE", str(tmp_path / "missing.json"))
    with pytest.raises(ValidationError, match="cannot read the keys file"):
        ServiceSettings()


def test_the_configuration_page_is_generated_from_the_models():
    committed = (ROOT / "docs" / "configuration.md").read_text()
    assert committed == configuration_markdown(), (
        "docs/configuration.md is stale: python -m service.config_docs > docs/configuration.md"
    )
    for model in (JobsConfig, ServiceSettings):
        for name in model.model_fields:
            assert f"`{name}`" in committed or name == "jobs"
