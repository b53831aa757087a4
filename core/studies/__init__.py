"""Studies behind `hapticloud bench`: deterministic runs against the simulator's ground truth."""
