"""The M-step (paper 3.4): measures (bone flow, motion similarity, lengths, tree), edits, joints, remap, schedule."""
