"""``child_environment()``: the environment of a child process that reads untrusted input (an
upload's probe, a job): the parent's, without the service's secrets. A child exploited through a
crafted video then cannot read the API key from ``/proc/self/environ``."""

from __future__ import annotations

import os

# The API key; the queue's URL, which holds its password (a job's process never uses the queue).
SECRETS = ("EVA_API_KEY", "EVA_QUEUE_URL")


def child_environment(**extra: str) -> dict[str, str]:
    """``os.environ`` without ``SECRETS``, plus ``extra``."""
    env = {k: v for k, v in os.environ.items() if k not in SECRETS}
    env.update(extra)
    return env
