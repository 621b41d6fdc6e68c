"""Where the model and a recording differ: normalised residuals, and later the
mismatch-discovery tool."""
