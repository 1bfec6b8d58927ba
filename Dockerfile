# The SITL test image: the flight service, the simulator, the closed-loop tests, and a PX4 SITL build when one
# is given. `scripts/container test` builds it with docker or podman and runs the SITL tests in it; compose.yaml
# runs the same image; docs/container.md says what is in it and why.
#
# Build arguments (an air-gapped site sets them to its own mirrors and builds this file unchanged):
#   BASE_IMAGE       a Debian 12 image with Python 3.11 and venv; pin it by digest (name@sha256:...)
#   PIP_INDEX_URL    the Python package index
#   DEBIAN_MIRROR    replaces http://deb.debian.org in the base's apt sources (empty: keep them)
#   EXTRAS           the project's extras: sim,dev runs the service, the simulator and the SITL tests
#   TORCH            a torch version (e.g. 2.13.0) to add the CPU build of torch; empty: none (the service
#                    runs the detector's ONNX export), which keeps about 700 MB out of the image
#   TORCH_INDEX_URL  the CPU wheel index; where it is out of reach, the `wheels` context must hold the wheel
# Named build contexts (`--build-context NAME=DIR`), each empty unless given:
#   px4              a PX4 SITL build (bin/px4 beside etc/), installed at /shared/px4-sitl, where the real-PX4
#                    tests look for it beside the checkout at /src
#   wheels           local wheels pip may take (PIP_FIND_LINKS)
# A build secret `pip_ca` (a CA bundle file) is given to pip and apt where a proxy re-signs TLS.
ARG BASE_IMAGE=python:3.11-slim-bookworm

FROM scratch AS px4
FROM scratch AS wheels

FROM ${BASE_IMAGE}
ARG PIP_INDEX_URL=https://pypi.org/simple
ARG DEBIAN_MIRROR=
ARG EXTRAS=sim,dev
ARG TORCH=
ARG TORCH_INDEX_URL=https://download.pytorch.org/whl/cpu

ENV DEBIAN_FRONTEND=noninteractive \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    PIP_NO_CACHE_DIR=1 \
    PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    VIRTUAL_ENV=/opt/venv \
    PATH=/opt/venv/bin:$PATH

# mosquitto and its clients: the MQTT tests start their own broker; Mesa EGL: the simulator renders the
# camera on the CPU (llvmpipe). The unit's systemd lint and the RealSense SDK are not SITL tests: left out.
RUN --mount=type=secret,id=pip_ca \
    if [ -n "$DEBIAN_MIRROR" ]; then \
        sed -i "s#http://deb.debian.org#$DEBIAN_MIRROR#g" /etc/apt/sources.list /etc/apt/sources.list.d/* 2>/dev/null || true; \
    fi \
 && if [ -s /run/secrets/pip_ca ]; then ca="-o Acquire::https::CaInfo=/run/secrets/pip_ca"; else ca=""; fi \
 && apt-get $ca update -qq \
 && apt-get $ca install -y -qq --no-install-recommends \
        mosquitto mosquitto-clients libegl1 libegl-mesa0 libgl1-mesa-dri libgl1 ca-certificates \
 && rm -rf /var/lib/apt/lists/* /var/cache/apt/*.bin

# The dependencies alone, read from pyproject.toml (a layer that survives code changes), with the build backend
# and `editables` for the editable install of the project after the whole tree is copied (its wheel carries
# config/ and models/).
WORKDIR /src
COPY pyproject.toml ./
COPY scripts/install-torch-cpu scripts/
RUN --mount=type=secret,id=pip_ca --mount=type=bind,from=wheels,target=/wheels \
    if [ -s /run/secrets/pip_ca ]; then export PIP_CERT=/run/secrets/pip_ca; fi \
 && export PIP_FIND_LINKS=/wheels \
 && python3 -m venv /opt/venv \
 && python -c 'import sys, tomllib; p = tomllib.load(open("pyproject.toml", "rb"))["project"]; \
extras = [e for e in sys.argv[1].split(",") if e]; \
build = tomllib.load(open("pyproject.toml", "rb"))["build-system"]["requires"]; \
print("\n".join(build + ["editables"] + p["dependencies"] + [d for e in extras for d in p["optional-dependencies"][e]]))' \
        "$EXTRAS" > /tmp/requirements.txt \
 && if [ -n "$TORCH" ]; then scripts/install-torch-cpu python "$TORCH"; fi \
 && pip install -q -r /tmp/requirements.txt \
 && rm /tmp/requirements.txt

# A non-root user runs the service and the tests; the simulator's camera socket and the service's status
# socket live in /run/wingman.
RUN useradd --create-home --uid 1000 wingman && install -d -o wingman /run/wingman && chown wingman /src
COPY --from=px4 / /shared/px4-sitl/
COPY --chown=wingman . .
RUN pip install -q --no-deps --no-build-isolation -e . && rm -rf /src/*.egg-info
USER wingman

# The closed-loop tests: the simulator over real UDP, a real mosquitto, and PX4 SITL when the image has it.
CMD ["python", "-m", "pytest", "-p", "no:cacheprovider", "-m", "sitl or mqtt_broker", "tests"]
