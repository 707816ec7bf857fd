# feedmon live monitor (feedmon run) in a container.
#
#   docker build -t feedmon .
#   docker run -d --name feedmon --stop-timeout 90 -p 127.0.0.1:7448:7448 \
#       -v feedmon-data:/var/lib/feedmon -v feedmon-logs:/var/log/feedmon \
#       -v "$PWD/monitor.toml:/etc/feedmon/monitor.toml:ro" feedmon
#
# * Configuration: /etc/feedmon/monitor.toml ([run] table of `feedmon run --config`; the image
#   ships deploy/monitor.toml there). Model files go to /var/lib/feedmon/models (feedmon identify),
#   tracker states to /var/lib/feedmon/state, MCAP logs to /var/log/feedmon.
# * Zenoh: the monitor listens on tcp/0.0.0.0:7448 inside the container (loopback would be
#   unreachable from outside it); publish the port only where the controller bridge runs, or
#   use a router (`--connect tls/router:7447 --zenoh-config ...`, deploy/zenoh/).
# * Stop: SIGTERM; the monitor drains its queue, finishes the MCAP file and saves the tracker
#   state. Give it time: `docker run --stop-timeout 90` / compose `stop_grace_period: 90s`
#   (Docker's default of 10 s can cut the MCAP short).
# * Health: `feedmon status` asks the monitor's status queryable (<prefix>/monitor/status) over
#   loopback; it exits 1 when no monitor answers within --timeout.
# Tested without a Docker engine by tests/test_deploy.py (same files copied, same commands run).

FROM python:3.11-slim-bookworm

ENV PYTHONUNBUFFERED=1 \
    PYTHONDONTWRITEBYTECODE=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    NUMBA_CACHE_DIR=/var/cache/feedmon/numba

RUN groupadd --system --gid 10001 feedmon \
 && useradd --system --uid 10001 --gid feedmon --home-dir /var/lib/feedmon --no-create-home \
        --shell /usr/sbin/nologin feedmon \
 && mkdir -p /var/lib/feedmon/models /var/lib/feedmon/state /var/log/feedmon /var/cache/feedmon/numba /etc/feedmon \
 && chown -R feedmon:feedmon /var/lib/feedmon /var/log/feedmon /var/cache/feedmon

WORKDIR /src
COPY pyproject.toml README.md ./
COPY kernels ./kernels
COPY feedio ./feedio
COPY monitor ./monitor
COPY replay ./replay
COPY feedmon ./feedmon
COPY bridge ./bridge
RUN pip install . \
 && cd / && rm -rf /src
COPY deploy/monitor.toml /etc/feedmon/monitor.toml

USER feedmon
# compile every Numba function the monitor reaches (tracker, online β, search, process monitors) into
# NUMBA_CACHE_DIR now, not at every container start (a cold compile takes ~1.5 min on one core; the
# cache is reused when the host CPU matches the build's, else `feedmon run` compiles before "ready")
RUN python -c "from monitor.warm import compile_all; compile_all()"
WORKDIR /var/lib/feedmon
VOLUME ["/var/lib/feedmon", "/var/log/feedmon"]
EXPOSE 7448/tcp
STOPSIGNAL SIGTERM

HEALTHCHECK --interval=30s --timeout=15s --start-period=120s --retries=3 \
    CMD ["feedmon", "status", "--timeout", "3", "--json"]

ENTRYPOINT ["feedmon", "run"]
CMD ["--config", "/etc/feedmon/monitor.toml", "--listen", "tcp/0.0.0.0:7448"]
