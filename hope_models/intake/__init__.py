"""What comes in: the inbox of handed-off episodes (inbox.py) and which components each one can
train (trainable.py)."""
