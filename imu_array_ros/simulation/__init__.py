"""Motion generators (random samples, hand twisting) and simulated measurements."""
