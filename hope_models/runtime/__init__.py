"""The torch-free serving side: BrainService (brain_service.py), which runs each component's NumPy
form (hope_models/components/<name>/numpy_form.py; what it accepts as a checkpoint: that
folder's checkpoint.py)."""
