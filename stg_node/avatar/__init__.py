"""STG-Avatar: animatable Gaussian avatars (SMPL + LBS + Spacetime Gaussians + flow-guided densification)."""
