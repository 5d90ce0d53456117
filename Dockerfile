# cellvision vision server, for the cell PC.
#   docker build -t cellvision .
#   docker run -d --name vision -p 7878:7878 -v /srv/cell:/config:ro -v vision-data:/data \
#       --device /dev/video0 cellvision
# The configuration is read from /config/cell.yaml; results and stored images go to /data.
# Reload the configuration without dropping connections: docker kill -s HUP vision
FROM python:3.11-slim

RUN apt-get update \
    && apt-get install -y --no-install-recommends libzbar0 \
    && rm -rf /var/lib/apt/lists/*

WORKDIR /opt/cellvision
COPY pyproject.toml README.md ./
COPY protocol ./protocol
COPY vision_server ./vision_server
COPY robot_client ./robot_client
COPY simulation ./simulation
COPY geometry ./geometry
RUN pip install --no-cache-dir . && rm -rf /opt/cellvision/build

RUN useradd --system --uid 10001 --create-home cellvision \
    && mkdir -p /config /data && chown cellvision /data
USER cellvision
VOLUME ["/data"]
EXPOSE 7878

# The container listens on every interface on purpose; outside a container the default is
# 127.0.0.1.
ENV CELLVISION_CONFIG=/config/cell.yaml
HEALTHCHECK --interval=10s --timeout=3s --start-period=5s --retries=3 \
    CMD ["vision-server", "ping", "--server", "127.0.0.1:7878"]
ENTRYPOINT ["vision-server"]
CMD ["serve", "--config", "/config/cell.yaml", "--host", "0.0.0.0", "--port", "7878"]
