"""Shared test helpers: ``scenes`` (rendered Anny scenes, in-memory datasets) and ``service``
(running the API and worker in tests), ``strategies`` (a render carrying a chosen screen-space
gradient, for density-control tests), ``render`` (small rasterizer scenes and a render with
gradients, for the rasterizer's tests)."""
