# syntax=docker/dockerfile:1
# photostereo: the HTTP API in a small image.
#   docker build -t photostereo .
#   docker run -p 8080:8080 -v photostereo-data:/data photostereo

FROM rust:1-bookworm AS build
WORKDIR /src
COPY . .
# The registry and target caches survive between builds (BuildKit); the binary is copied
# out of the cached target directory in the same step.
RUN --mount=type=cache,target=/usr/local/cargo/registry \
    --mount=type=cache,target=/src/target \
    cargo build --release --locked --bin photostereo \
    && install -m 0755 target/release/photostereo /usr/local/bin/photostereo

FROM debian:bookworm-slim
RUN useradd --system --uid 10001 --user-group --home-dir /data --shell /usr/sbin/nologin photostereo \
    && mkdir -p /data \
    && chown photostereo:photostereo /data
COPY --from=build /usr/local/bin/photostereo /usr/local/bin/photostereo
USER 10001:10001
ENV PHOTOSTEREO_LISTEN=0.0.0.0:8080 \
    PHOTOSTEREO_DATA_DIR=/data
EXPOSE 8080
VOLUME /data
# The binary checks itself (the image has no curl); set PHOTOSTEREO_HEALTHCHECK_URL when
# the port changes.
HEALTHCHECK --interval=30s --timeout=5s --start-period=10s --retries=3 \
    CMD ["photostereo", "healthcheck"]
ENTRYPOINT ["photostereo"]
CMD ["serve"]
