"""Reports: result tables, figures and the per-warp views they are drawn from."""
