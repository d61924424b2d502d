# Prism: multi-stage image. The build stage installs the -dev packages with the project's own setup
# script and builds; the runtime stage carries only the runtime libraries and the installed binaries.
#   ../shared/tools/container.sh build prism:dev        (no Docker engine needed; BUILDAH_FORMAT=docker
#                                                         keeps the HEALTHCHECK, which OCI images drop)
#   docker build -t prism .                              (where Docker runs)
#   docker run -p 5555:5555 -p 9100:9100 -v prism-data:/var/lib/prism prism
# Configuration: prism-server flags after the image name, or the environment read by the entrypoint
# (deploy/docker/entrypoint.sh): PRISM_BIND, PRISM_METRICS, PRISM_DATA_DIR, PRISM_CONFIG,
# PRISM_ADVERTISE, PRISM_MAX_SESSIONS, PRISM_LOG_LEVEL. Any other command runs as given
# (docker run prism prism-synth --list-presets).

FROM debian:bookworm AS build
ENV DEBIAN_FRONTEND=noninteractive
COPY scripts/setup.sh /src/scripts/setup.sh
RUN bash /src/scripts/setup.sh && rm -rf /var/lib/apt/lists/*
COPY . /src
# The compiler cache survives rebuilds of the source layer (BuildKit and buildah cache mounts).
RUN --mount=type=cache,target=/root/.cache/ccache,id=prism-ccache \
    cmake -S /src -B /build -G Ninja -DCMAKE_BUILD_TYPE=Release \
      -DPRISM_BUILD_TESTS=OFF -DPRISM_BUILD_BENCHMARKS=OFF -DCMAKE_INSTALL_PREFIX=/opt/prism \
      -DPRISM_PYTHON_INSTALL_DIR=lib/python3/dist-packages \
 && cmake --build /build \
 && cmake --install /build --strip \
 && install -m 0755 /src/deploy/docker/entrypoint.sh /opt/prism/bin/prism-entrypoint

FROM debian:bookworm AS runtime
ENV DEBIAN_FRONTEND=noninteractive
# Exactly the libraries the installed binaries and libprism_client link against (readelf -d NEEDED),
# and Python with numpy for the prism_client bindings (scripted clients in the image).
RUN apt-get update -qq \
 && apt-get install -y -qq --no-install-recommends \
      libopencv-core406 libopencv-imgproc406 libopencv-imgcodecs406 libopencv-calib3d406 libopencv-video406 \
      libopencv-videoio406 libopencv-contrib406 \
      libpcl-common1.13 libpcl-search1.13 libpcl-kdtree1.13 libpcl-octree1.13 \
      libprotobuf32 libzmq5 libdraco7 libjpeg62-turbo libpng16-16 libyaml-cpp0.7 libmicrohttpd12 \
      python3 python3-numpy \
 && rm -rf /var/lib/apt/lists/* \
 && groupadd --system --gid 10001 prism \
 && useradd --system --uid 10001 --gid prism --create-home --home-dir /var/lib/prism --shell /usr/sbin/nologin prism \
 && mkdir -p /var/lib/prism/data && chown -R prism:prism /var/lib/prism
COPY --from=build /opt/prism /opt/prism
RUN echo /opt/prism/lib > /etc/ld.so.conf.d/prism.conf && ldconfig
ENV PATH=/opt/prism/bin:$PATH \
    PRISM_MESH_DIR=/opt/prism/share/prism/meshes \
    PYTHONPATH=/opt/prism/lib/python3/dist-packages \
    PRISM_BIND=tcp://0.0.0.0:5555 \
    PRISM_METRICS=0.0.0.0:9100 \
    PRISM_DATA_DIR=/var/lib/prism/data
USER prism
WORKDIR /var/lib/prism
VOLUME ["/var/lib/prism"]
# 5555: ZeroMQ sessions (ROUTER). 9100: HTTP /metrics, /healthz, /allocate.
EXPOSE 5555/tcp 9100/tcp
HEALTHCHECK --interval=15s --timeout=5s --start-period=10s --retries=3 \
  CMD prism-probe --timeout-ms 3000 "http://127.0.0.1:${PRISM_METRICS##*:}/healthz" > /dev/null || exit 1
STOPSIGNAL SIGTERM
ENTRYPOINT ["prism-entrypoint"]
CMD ["prism-server"]
