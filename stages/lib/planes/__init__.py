"""The planes a photo offers for placing objects: the search over a depth map and the pixels of each plane."""
