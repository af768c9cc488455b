"""Learning layer (pure: no ROS, no file I/O).

- ``gp``: ``DisturbanceGP``, one exact GP per disturbance dimension (paper: "Disturbance
  Estimation"), fitted with GPyTorch, predicted in closed form from cached factors.
- ``networks``, ``buffers``, ``sac``: SAC with the SAC-RCBF training modes (unconstrained,
  baseline, baseline_compensator, diff, modular); the safety layer is injected as a callable.
- ``model_based``: ``ModelRollout``, k-step synthetic transitions (Algorithm 1).
"""
from rcbf_ros.core.torch_import import bind_torch

bind_torch()  # learning runs on torch: the constraint modules that wait for it get it now
