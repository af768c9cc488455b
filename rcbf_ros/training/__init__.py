"""ROS-free training: the learner core shared by the node and the in-process trainer."""
