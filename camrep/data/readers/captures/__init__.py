"""Posed captures in the formats the field uses: NeRF / instant-ngp / nerfstudio `transforms.json`
(`nerf`), LLFF `poses_bounds.npy` (`llff`) and COLMAP sparse models (`colmap`), read into one
`cameras.Capture` (camera-to-world, OpenCV axes), normalised to a camrep setting (`normalize`) and
served as view records (`source.CaptureSource`, the `prepare` sources nerf, llff, colmap and their
`_6dof` variants)."""
