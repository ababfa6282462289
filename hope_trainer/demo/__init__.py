"""The end-to-end demo (`hope-trainer demo`): the session that drives the services, and its report."""
