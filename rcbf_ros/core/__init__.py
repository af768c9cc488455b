"""The math of the safety filter, pure: dynamics, barriers, Lie derivatives, the one RCBF-QP
builder, the per-step filter and the differentiable QP; no ROS, no messages, no file I/O."""
