"""nsd-export: per-subject results of a trained decomposition in the formats the field reads."""
