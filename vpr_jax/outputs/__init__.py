"""What a sweep leaves on disk: results.csv, TensorBoard runs, figures, and the log
directory's own rules (which configurations may share one, one writer at a time)."""
