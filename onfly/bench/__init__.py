"""The embedded benchmark: tasks, methods, the episode runner and the paper's metrics."""
