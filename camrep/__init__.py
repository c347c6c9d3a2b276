"""camrep: neural representation of camera pose (Zhu et al., CVPR 2021) in JAX/Flax."""
