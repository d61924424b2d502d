#!/bin/sh
# The image's entrypoint. "prism-server [FLAGS]" (the default command), or only flags, starts the
# server configured from the environment, with the flags applied after it (a flag wins over the
# environment); any other command runs unchanged (prism-client, prism-synth, sh, ...).
#   PRISM_BIND          ZeroMQ endpoint                         (image default tcp://0.0.0.0:5555)
#   PRISM_METRICS       HTTP /metrics /healthz /allocate        (image default 0.0.0.0:9100)
#   PRISM_DATA_DIR      sessions' persisted maps (the volume)   (image default /var/lib/prism/data)
#   PRISM_CONFIG        a 'key = value' config file             (optional)
#   PRISM_ADVERTISE     endpoint /allocate hands out, e.g. the pod's DNS name (optional)
#   PRISM_MAX_SESSIONS  concurrent sessions                     (optional)
#   PRISM_LOG_LEVEL     debug|info|warning|error                (optional)
#   PRISM_CURVE_KEYS    CURVE key pair file (prism-server keygen --out FILE); with
#   PRISM_ALLOWED_CLIENTS  the client public keys admitted, one per line (both or neither)
set -eu

if [ "$#" -eq 0 ] || [ "$1" = "prism-server" ]; then
  [ "$#" -gt 0 ] && shift
elif [ "${1#--}" = "$1" ]; then
  exec "$@"
fi

set -- --bind "${PRISM_BIND:-tcp://0.0.0.0:5555}" \
       --metrics "${PRISM_METRICS:-0.0.0.0:9100}" \
       --data-dir "${PRISM_DATA_DIR:-/var/lib/prism/data}" \
       ${PRISM_ADVERTISE:+--advertise "$PRISM_ADVERTISE"} \
       ${PRISM_MAX_SESSIONS:+--max-sessions "$PRISM_MAX_SESSIONS"} \
       ${PRISM_LOG_LEVEL:+--log-level "$PRISM_LOG_LEVEL"} \
       ${PRISM_CURVE_KEYS:+--curve-keys "$PRISM_CURVE_KEYS"} \
       ${PRISM_ALLOWED_CLIENTS:+--allowed-clients "$PRISM_ALLOWED_CLIENTS"} \
       "$@"
# --config is read before every flag by prism-server, so its place in the list does not matter.
if [ -n "${PRISM_CONFIG:-}" ]; then set -- --config "$PRISM_CONFIG" "$@"; fi
mkdir -p "${PRISM_DATA_DIR:-/var/lib/prism/data}" 2>/dev/null || true
exec prism-server "$@"
