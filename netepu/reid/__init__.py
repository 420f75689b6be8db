"""Re-identification: identities across cameras and time, figures, a CNN baseline."""
