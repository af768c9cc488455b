"""Training without middleware: Algorithm 1's agent (shared with the learner node), the
in-process run of ``rcbf_ros train``, and the files a run leaves (checkpoints, metrics, policy)."""
