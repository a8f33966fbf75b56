"""Studies of record built on the stages: the paper's experiment and the robust-feature selection."""
