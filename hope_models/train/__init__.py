"""One training loop for every HOPE component: resumable, guarded, logged."""
