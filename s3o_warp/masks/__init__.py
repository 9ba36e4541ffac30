"""Masks for a video that has none: a box around the object on one frame (or a few) gives a mask on every frame
(make.py writes the sequence folder; grabcut.py is the default segmenter, sam2.py the optional one)."""
