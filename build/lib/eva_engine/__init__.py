"""EVA engine: expressive Gaussian human avatars from monocular RGB video.

Everything scientific lives here (rendering, body models, data, alignment, training, evaluation).
It imports without the service stack (FastAPI, huey): `service/` and `jobs/` depend on it, never
the other way round.
"""

__version__ = "0.1.0"
