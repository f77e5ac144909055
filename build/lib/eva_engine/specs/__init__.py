"""Torch-free request schemas (pydantic) that the CLI, the job queue and the API share: a camera
(``camera``) and an animation's options (``animation``). The queue's processes validate and
budget jobs with them without loading torch (``python -m jobs probe``'s memory cap)."""
