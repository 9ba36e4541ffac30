"""The M-step (paper 3.4): bone flow and measures, skeleton edits and their schedule."""
