"""Orchestration between the HTTP layer and the vision library in app.core."""
