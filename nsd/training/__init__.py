"""NSD training: the task (named loss terms), the pose-regressor task, image losses, the driver."""
