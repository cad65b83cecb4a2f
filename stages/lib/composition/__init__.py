"""Scene composition shared by the compose and cut_and_paste stages: placement, object rendering,
occlusion, pixel augmentation, blending, parallel image generation and dataset writing."""
