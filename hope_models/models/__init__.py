"""The HOPE v1 seed components: VQ-VAE tokenizer, diagonal SSM layer, Fast Loop and Mid Loop."""
