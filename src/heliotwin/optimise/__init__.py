"""Acting on the learned plant: aim-point optimisation over the differentiable field model."""
