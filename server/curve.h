// ZeroMQ CURVE for prism-server: key files, the client allow-list and the ZAP handler that enforces it
// (RFC 27). The ZAP socket is polled by the transport thread like the ROUTER; libzmq's I/O threads wait
// for its answer, so a handshake never blocks serving.
#pragma once

#include <set>
#include <string>

#include <zmq.hpp>

#include "core/util/status.h"

namespace prism::server {

struct CurveKeyPair {
  std::string public_key;  // Z85, 40 characters
  std::string secret_key;
};

// UNAVAILABLE when libzmq was built without CURVE.
StatusOr<CurveKeyPair> GenerateCurveKeyPair();
// "public = KEY" and "secret = KEY" lines; the file is created with mode 0600.
Status WriteCurveKeyFile(const std::string& path, const CurveKeyPair& keys);
StatusOr<CurveKeyPair> ReadCurveKeyFile(const std::string& path);
// One Z85 public key per line; lines starting with '#' and blank lines ignored; "public = KEY" lines
// (a key file) accepted too. (Z85 keys may contain '#' and '='.)
StatusOr<std::set<std::string>> ReadAllowList(const std::string& path);

// Answers one pending ZAP request on `zap` (a REP bound to inproc://zeromq.zap.01): 200 for a CURVE
// client whose public key is in `allowed`, 400 otherwise. Returns true when it admitted the client.
bool HandleZapRequest(zmq::socket_t& zap, const std::set<std::string>& allowed, std::string* client_key);

// True for endpoints only this machine can reach (tcp loopback, ipc://, inproc://).
bool IsLoopbackEndpoint(const std::string& endpoint);

}  // namespace prism::server
