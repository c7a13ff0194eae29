"""State estimation through hybrid executions."""
