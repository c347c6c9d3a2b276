"""View-synthesis training (paper sections 3.3-3.4, 4.1-4.3): the train step that combines the
reconstruction and rotation losses, the loop, held-out evaluation, noise robustness and Gram maps,
and the `python -m camrep.synthesis.evaluate` command."""
