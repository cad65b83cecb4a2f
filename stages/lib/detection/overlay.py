"""Detections drawn on their photo: tinted masks (and their outlines), boxes, "class score" labels."""
from __future__ import annotations

import cv2
import numpy as np

PALETTE = np.array([[230, 25, 75], [60, 180, 75], [0, 130, 200], [245, 130, 48], [145, 30, 180],
                    [70, 240, 240], [240, 50, 230], [210, 245, 60]], np.uint8)  # RGB, one per class (label - 1)


def draw_detections(image: np.ndarray, detections: dict, names: list[str], score_threshold: float,
                    outlines: bool = False) -> np.ndarray:
    """The image [H, W, 3] uint8 with masks tinted, boxes and "name score" labels drawn for the detections (boxes
    [N, 4], scores [N], labels [N] 1..K, masks [N, H, W] bool) scoring at least score_threshold; with `outlines`,
    also each mask's outline in its class's colour, and the labels in white on a tag of that colour (legible on any
    photo)."""
    canvas = image.copy()
    for box, score, label, mask in zip(detections["boxes"], detections["scores"], detections["labels"], detections["masks"]):
        if score < score_threshold:
            continue
        colour = PALETTE[(int(label) - 1) % len(PALETTE)]
        canvas[mask] = (0.5 * canvas[mask] + 0.5 * colour).astype(np.uint8)
        x0, y0, x1, y1 = (int(round(v)) for v in box)
        c = tuple(int(v) for v in colour)
        text = f"{names[int(label) - 1]} {score:.2f}"
        cv2.rectangle(canvas, (x0, y0), (x1, y1), c, 2)
        if not outlines:
            cv2.putText(canvas, text, (x0, max(12, y0 - 4)), cv2.FONT_HERSHEY_SIMPLEX, 0.45, c, 1, cv2.LINE_AA)
            continue
        contours, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
        cv2.drawContours(canvas, contours, -1, c, 2, cv2.LINE_AA)
        (width, height), base = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, 0.45, 1)
        top = max(y0 - height - base - 4, 0)
        cv2.rectangle(canvas, (x0 - 1, top), (x0 + width + 4, top + height + base + 4), c, cv2.FILLED)
        cv2.putText(canvas, text, (x0 + 2, top + height + 2), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1,
                    cv2.LINE_AA)
    return canvas
