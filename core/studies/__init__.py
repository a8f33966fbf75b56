"""Studies: the experiments of record built on the stages (the paper's experiment, the robust-feature selection)."""
