"""The E-step (paper 3.3): the reconstruction objective, camera hypotheses, frame windows, leg crossings."""
