"""What a person reads: plots, video, report, notebook display, seed statistics, reference policies, export."""
