"""Definition and validation: modes, transitions, hybrid systems, shape checks at definition time, and
the kernels that evaluate a system's functions for the mode chosen at run time."""
