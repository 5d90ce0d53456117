# cellvision on the cell PC: the vision server (the entrypoint) and, in the same image, the
# robot client (`robot-client`) and the protocol's conformance suite, for checks from inside.
#   docker build -t cellvision .
#   podman build --format docker -t cellvision .   # podman drops HEALTHCHECK without --format docker
#   docker run -d --name vision -p 127.0.0.1:7878:7878 \
#       -v "$PWD/examples/container:/config:ro" -v vision-data:/data cellvision
# The configuration is read from /config/cell.yaml; the result log, stored images and any other
# state go to /data (examples/container/cell.yaml is a ready one, with simulated cameras).
# Add --device /dev/video0 only for a real camera attached to the cell PC.
# Reload the configuration without dropping connections: docker kill -s HUP vision
# DEFAULTS ARE OPEN: no token, plaintext, every interface inside the container, RELOAD allowed;
# see the README, "On the cell PC: the server in a container", to secure it.

# The base image, pinned by exact tag (pin a digest as well with
# --build-arg BASE_IMAGE=python:3.11.13-slim-bookworm@sha256:...). Any Debian-like image with
# python3 >= 3.11 and its venv module works: the tests build one with debootstrap.
ARG BASE_IMAGE=python:3.11.13-slim-bookworm
FROM ${BASE_IMAGE}

RUN apt-get update \
    && apt-get install -y --no-install-recommends libzbar0 \
    && rm -rf /var/lib/apt/lists/*

# A virtual environment: a distribution's python3 refuses system-wide pip installs (PEP 668).
RUN python3 -m venv /opt/venv
ENV PATH=/opt/venv/bin:$PATH

# The dependencies in their own layer, rebuilt only when pyproject.toml changes; with them the
# build backend, so that installing the sources below needs no network. The plant's front-ends
# come in the image too (the extras opcua and mqtt: OPC UA and results to a broker), and uvloop
# for `server: event_loop: uvloop`.
WORKDIR /opt/cellvision
COPY pyproject.toml ./
RUN python3 -c "import tomllib; p = tomllib.load(open('pyproject.toml', 'rb')); \
extras = p['project']['optional-dependencies']; \
print('\n'.join(p['project']['dependencies'] + p['build-system']['requires'] \
                + extras['opcua'] + extras['mqtt'] + extras['uvloop']))" \
        > /tmp/requirements.txt \
    && pip install --no-cache-dir -r /tmp/requirements.txt \
    && rm /tmp/requirements.txt

COPY README.md ./
COPY protocol ./protocol
COPY vision_server ./vision_server
COPY robot_client ./robot_client
COPY simulation ./simulation
COPY geometry ./geometry
COPY yamlfile ./yamlfile
COPY wireio ./wireio
RUN pip install --no-cache-dir --no-deps --no-build-isolation . \
    && rm -rf /opt/cellvision/build

# In the group `video` so that a camera passed with --device can be opened.
RUN useradd --uid 10001 --user-group --groups video --create-home --shell /usr/sbin/nologin \
        cellvision \
    && mkdir -p /config /data && chown cellvision /data
USER cellvision
VOLUME ["/data"]
EXPOSE 7878 4840

# The container listens on every interface on purpose; outside a container the default is
# 127.0.0.1.
ENV CELLVISION_CONFIG=/config/cell.yaml
HEALTHCHECK --interval=10s --timeout=3s --start-period=5s --retries=3 \
    CMD ["vision-server", "ping", "--server", "127.0.0.1:7878"]
ENTRYPOINT ["vision-server"]
CMD ["serve", "--config", "/config/cell.yaml", "--host", "0.0.0.0", "--port", "7878"]
