# Prism: multi-stage image. The build stage installs the -dev packages with the project's own
# setup script and builds; the runtime stage carries only runtime libraries and the binaries.
#   ../shared/tools/container.sh build prism:dev        (no Docker engine needed)
#   docker build -t prism .                              (where Docker runs)

FROM debian:bookworm AS build
ENV DEBIAN_FRONTEND=noninteractive
COPY scripts/setup.sh /src/scripts/setup.sh
RUN bash /src/scripts/setup.sh && rm -rf /var/lib/apt/lists/*
COPY . /src
RUN cmake -S /src -B /build -G Ninja -DCMAKE_BUILD_TYPE=Release \
      -DPRISM_BUILD_TESTS=OFF -DPRISM_BUILD_BENCHMARKS=OFF -DCMAKE_INSTALL_PREFIX=/opt/prism \
 && cmake --build /build \
 && cmake --install /build

FROM debian:bookworm AS runtime
ENV DEBIAN_FRONTEND=noninteractive
RUN apt-get update -qq \
 && apt-get install -y -qq --no-install-recommends \
      libopencv-core406 libopencv-imgproc406 libopencv-imgcodecs406 libopencv-contrib406 libprotobuf32 \
      libpcl-common1.13 libpcl-kdtree1.13 libpcl-search1.13 libpcl-octree1.13 ca-certificates \
 && rm -rf /var/lib/apt/lists/* \
 && useradd --system --create-home --home-dir /var/lib/prism --shell /usr/sbin/nologin prism
COPY --from=build /opt/prism /opt/prism
ENV PATH=/opt/prism/bin:$PATH \
    PRISM_MESH_DIR=/opt/prism/share/prism/meshes
USER prism
WORKDIR /var/lib/prism
VOLUME ["/var/lib/prism"]
CMD ["prism-synth", "--list-presets"]
