"""Animation: make an avatar perform a motion -- from a video of anyone, a dataset, or a JSON file
of poses -- and write it as an mp4 (``eva animate``, ``POST /avatars/{id}/animations``).

    from eva_engine.animate import AnimationConfig, animate, load_driving, write_animation
    driving = load_driving("clip_of_someone_signing.mp4", avatar.body)   # preprocess + align
    write_animation("out.mp4", animate(avatar, driving, AnimationConfig(side_by_side=True)))

Pieces: ``driving`` (sequences and their sources), ``retarget`` (one person's motion onto
another's body), ``timing`` (smoothing and resampling over time), ``animation`` (render, encode),
``controls`` (named pose sliders for people).
"""

from eva_engine.animate.animation import Animation, animate, write_animation
from eva_engine.animate.driving import (
    DrivingError,
    DrivingSequence,
    PoseSequence,
    driving_from_dataset,
    driving_from_poses,
    driving_from_video,
    load_driving,
)
from eva_engine.animate.retarget import body_height, recenter, retarget
from eva_engine.animate.timing import resample_params, smooth_params
from eva_engine.specs.animation import AnimationConfig, AnimationError

__all__ = [
    "Animation",
    "AnimationConfig",
    "AnimationError",
    "DrivingError",
    "DrivingSequence",
    "PoseSequence",
    "animate",
    "body_height",
    "driving_from_dataset",
    "driving_from_poses",
    "driving_from_video",
    "load_driving",
    "recenter",
    "resample_params",
    "retarget",
    "smooth_params",
    "write_animation",
]
