"""The paper's experiments, redone: one module per experiment, each with a `Params` dataclass,
`run(params) -> result` (the computation, no files) and `report(result, out_dir)` (figures, JSON
and report.md). `krang experiment <name>` (krang_cli/experiment.py) only parses the arguments into
Params.

* table2: Table II in closed-loop simulation (online learning, then stand-up-and-balance runs).
* adrc_vs_lqr: ADRC and plain LQR with the same wrong CoM (stand-up, push, pose change).
* learning: the paper's simulation redone, learning curves and the real hardware data.
"""
