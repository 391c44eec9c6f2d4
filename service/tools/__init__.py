"""Tools beside the product: the demo, the simulated ArduSub endpoint, plots, metrics and
benchmarks. The daemon does not depend on them (replay sinks load plots and metrics lazily)."""
