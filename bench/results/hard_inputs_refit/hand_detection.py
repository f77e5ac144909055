"""MediaPipe on a clip's frames three ways: Holistic (the product's detector, video mode), Hands on
the full frame, and Hands on a square around each pose wrist (1.2 forearm lengths, shifted half a
forearm past the wrist, resized to 256 px). ``python hand_detection.py <video>``."""

import sys

import cv2
import mediapipe as mp
import numpy as np

capture = cv2.VideoCapture(sys.argv[1])
frames = []
while True:
    ok, frame = capture.read()
    if not ok:
        break
    frames.append(cv2.cvtColor(frame, cv2.COLOR_BGR2RGB))
holistic = mp.solutions.holistic.Holistic(static_image_mode=False, model_complexity=1)
hands = mp.solutions.hands.Hands(static_image_mode=True, max_num_hands=2, min_detection_confidence=0.3)
by_holistic, on_crops, on_frames = [0, 0], [0, 0], 0
for frame in frames:
    result = holistic.process(frame)
    by_holistic[0] += result.left_hand_landmarks is not None
    by_holistic[1] += result.right_hand_landmarks is not None
    on_frames += len(hands.process(frame).multi_hand_landmarks or [])
    if result.pose_landmarks is None:
        continue
    h, w = frame.shape[:2]
    landmarks = result.pose_landmarks.landmark
    padded = cv2.copyMakeBorder(frame, 512, 512, 512, 512, cv2.BORDER_CONSTANT, value=(255, 255, 255))
    for side, (wrist, elbow) in enumerate(((15, 13), (16, 14))):
        wx, wy = landmarks[wrist].x * w, landmarks[wrist].y * h
        ex, ey = landmarks[elbow].x * w, landmarks[elbow].y * h
        half = max(48.0, 1.2 * float(np.hypot(wx - ex, wy - ey)))
        cx, cy = wx + 0.5 * (wx - ex), wy + 0.5 * (wy - ey)
        x0, y0 = int(cx - half) + 512, int(cy - half) + 512
        crop = padded[y0 : y0 + int(2 * half), x0 : x0 + int(2 * half)]
        if crop.size:
            on_crops[side] += bool(hands.process(cv2.resize(crop, (256, 256))).multi_hand_landmarks)
print(
    f"{len(frames)} frames: Holistic found the left / right hand in {by_holistic}; Hands on the full "
    f"frames found {on_frames} hands in all; Hands on the wrists' squares found {on_crops}"
)
