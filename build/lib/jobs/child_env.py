"""``child_environment()``: the environment of a child process that reads untrusted input (an
upload's probe, a job): the parent's, without the service's secrets. A child exploited through a
crafted video then cannot read the API key from ``/proc/self/environ``."""

from __future__ import annotations

import os

# The API key; the queue's URL, which holds its password (a job's process never uses the queue);
# the records' URL (a job's process gets it in its spec, the probe never needs it).
SECRETS = ("EVA_API_KEY", "EVA_QUEUE_URL", "EVA_RECORDS_URL")
# The bucket's credentials (``jobs.storage_s3``): a job reads its upload and publishes its result
# there; the probe never touches the bucket.
STORAGE_SECRETS = ("AWS_ACCESS_KEY_ID", "AWS_SECRET_ACCESS_KEY", "AWS_SESSION_TOKEN")


def child_environment(storage: bool = False, **extra: str) -> dict[str, str]:
    """``os.environ`` without ``SECRETS`` (and without ``STORAGE_SECRETS`` unless ``storage``),
    plus ``extra``."""
    hidden = SECRETS if storage else SECRETS + STORAGE_SECRETS
    env = {k: v for k, v in os.environ.items() if k not in hidden}
    env.update(extra)
    return env
