# Prometheus from Debian's package, for an engine that cannot pull
# prom/prometheus (no registry): the command line, paths, port and user of
# the upstream image, so that docker-compose.yml's prometheus service runs it
# unchanged. docker-compose.offline.yml builds and uses it:
#
#   docker-compose -f deploy/compose/docker-compose.yml \
#     -f deploy/compose/docker-compose.offline.yml up -d
ARG DEBIAN_SLIM_IMAGE=debian:12-slim
FROM ${DEBIAN_SLIM_IMAGE}
# wget: the service's health check.
RUN apt-get update \
 && DEBIAN_FRONTEND=noninteractive apt-get install -y --no-install-recommends prometheus wget \
 && rm -rf /var/lib/apt/lists/* \
 && mkdir -p /prometheus \
 && chown nobody:nogroup /prometheus
USER nobody
WORKDIR /prometheus
EXPOSE 9090
ENTRYPOINT ["/usr/bin/prometheus"]
CMD ["--config.file=/etc/prometheus/prometheus.yml", "--storage.tsdb.path=/prometheus"]
