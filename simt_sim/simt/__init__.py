"""The warp-level SIMT model: lane-mask counters, the replay driver, results and their model
cards, GPU configurations, the memory model. Each scheme's own replay is in
:mod:`simt_sim.schemes`."""
