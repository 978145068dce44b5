# The policy service: ONNX Runtime backend, no torch. Build from the repo root after training and
# exporting the policies into models/:
#   docker build -t pusht-service . && docker run -p 8000:8000 pusht-service
# tests/test_service_docker.py performs this file's COPY and `pip install` steps in a fresh venv.
FROM python:3.11-slim

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    PUSHT_MODELS_DIR=/app/models \
    PUSHT_BACKEND=onnx

RUN useradd --create-home --uid 10001 --shell /usr/sbin/nologin app
WORKDIR /app

# Only what the serving extra needs: the env package (seeds, spec), the acting interface (card reader,
# ONNX Runtime backend) and the service; no training code.
COPY pyproject.toml README.md ./
COPY pusht ./pusht
COPY policies ./policies
COPY acting ./acting
COPY service ./service
RUN pip install ".[serve]"

COPY models ./models

USER app
EXPOSE 8000
HEALTHCHECK --interval=15s --timeout=3s --start-period=30s --retries=3 \
    CMD ["python", "-c", "import sys, urllib.request; sys.exit(0 if urllib.request.urlopen('http://127.0.0.1:8000/readyz', timeout=2).status == 200 else 1)"]
# python -m service: uvicorn with a header deadline, connection caps and a bounded shutdown (README: security model).
CMD ["python", "-m", "service", "--host", "0.0.0.0", "--port", "8000"]
