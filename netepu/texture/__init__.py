"""NeTePu's texture VAE: codes that render an individual in any pose or view and re-identify it."""
