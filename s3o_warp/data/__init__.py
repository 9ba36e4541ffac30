"""Reading a sequence: frames, masks, crops, optical flow, keypoints and the fit's frame stores."""
