"""Networks: motion VAE, latent denoiser, text encoders."""
