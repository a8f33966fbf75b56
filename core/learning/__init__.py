"""Learning: damage models, their training and training sets, and classifying a pair with a model."""
