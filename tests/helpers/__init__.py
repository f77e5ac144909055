"""Shared test helpers: ``scenes`` (rendered Anny scenes, in-memory datasets) and ``service``
(running the API and worker in tests)."""
