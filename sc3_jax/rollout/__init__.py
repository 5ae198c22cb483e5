"""The closed loop on device (``rollout``: Algorithm 1), its imagined state (``imagination_state``), the learned
state head, and the rollouts' files on disk (``rollout_io``)."""
