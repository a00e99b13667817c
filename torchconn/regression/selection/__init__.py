"""Model selection: held-out skill, the complexity ladder and the connection alone."""
