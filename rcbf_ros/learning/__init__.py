"""Learning, pure (no ROS, no file I/O): the GP disturbance model, SAC with the SAC-RCBF
training modes, replay buffers and model rollouts; the safety layer comes in as a callable."""
from rcbf_ros.core.torch_import import bind_torch

bind_torch()  # learning runs on torch: the constraint modules that wait for it get it now
