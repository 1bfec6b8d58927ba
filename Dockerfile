# The SITL test suite in a container: `docker compose run --rm tests` (see compose.yaml, docs/service.md).
# The test suite does not build it (it runs without a Docker engine); kept simple so it is easy to check.
FROM python:3.11-slim-bookworm

ENV DEBIAN_FRONTEND=noninteractive \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    PIP_NO_CACHE_DIR=1 \
    PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PY=/opt/venv/bin/python

# mosquitto (and its clients): the MQTT tests start their own broker; systemd: `systemd-analyze` lints the unit;
# Mesa EGL: the simulator renders the camera on the CPU; libusb: pyrealsense2 imports.
RUN apt-get update \
 && apt-get install -y --no-install-recommends \
        mosquitto mosquitto-clients systemd libusb-1.0-0 libegl1 libegl-mesa0 libgl1-mesa-dri libgl1 ca-certificates \
 && rm -rf /var/lib/apt/lists/*

# Dependencies first (a layer that survives code changes). torch from the CPU index: PyPI's default
# Linux wheel is the multi-GB CUDA build.
WORKDIR /src
COPY pyproject.toml README.md ./
COPY companion/__init__.py companion/__init__.py
COPY sitl/__init__.py sitl/__init__.py
RUN python -m venv /opt/venv \
 && /opt/venv/bin/pip install -q torch==2.13.0 --index-url https://download.pytorch.org/whl/cpu \
 && /opt/venv/bin/pip install -q ".[sim,dev,cluster,realsense]" \
 && /opt/venv/bin/pip uninstall -q -y wingman

COPY . .
RUN /opt/venv/bin/pip install -q --no-deps -e . \
 && useradd --create-home --uid 1000 tester \
 && chown -R tester /src
USER tester

# scripts/check: ruff, mypy, the import rules, and the tests (SITL, MQTT, Ray on the loopback address, ...).
CMD ["scripts/check"]
