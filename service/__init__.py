"""The policy service: `uvicorn service.app:app` answers POST /act from the exported policies in models/."""
