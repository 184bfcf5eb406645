"""Training entries: one per stage (VAE, denoiser)."""
