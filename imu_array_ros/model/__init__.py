"""The array and its sensor model: description (YAML schema), layouts, rigid-body
kinematics, identifiability, the measurement model and its error terms, and the
in-memory sample containers."""
