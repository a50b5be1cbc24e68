"""The HTTP API's bodies as pydantic models, one module per domain: what /openapi.json declares and
the routes answer (problem.py: the error body every route shares)."""
