"""Robot programs: the vendor-neutral program IR, the motions of a work package,
feasibility along every move, compilation, and one writer per format
(:mod:`fabflow.programs.writers`)."""
