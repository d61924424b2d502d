#include "server/curve.h"

#include <sys/stat.h>

#include <fstream>
#include <vector>

namespace prism::server {
namespace {

std::string Trim(const std::string& s) {
  const size_t b = s.find_first_not_of(" \t\r\n"), e = s.find_last_not_of(" \t\r\n");
  return b == std::string::npos ? "" : s.substr(b, e - b + 1);
}

bool IsZ85Key(const std::string& key) {
  if (key.size() != 40) return false;
  uint8_t raw[32];
  return zmq_z85_decode(raw, key.c_str()) != nullptr;
}

}  // namespace

StatusOr<CurveKeyPair> GenerateCurveKeyPair() {
  if (!zmq_has("curve")) return UnavailableError("this libzmq was built without CURVE");
  char pub[41], sec[41];
  if (zmq_curve_keypair(pub, sec) != 0) return InternalError("zmq_curve_keypair failed");
  return CurveKeyPair{pub, sec};
}

Status WriteCurveKeyFile(const std::string& path, const CurveKeyPair& keys) {
  const mode_t old = umask(077);
  {
    std::ofstream out(path, std::ios::trunc);
    out << "# prism CURVE key pair: give 'public' to the other side, keep 'secret' here\npublic = " << keys.public_key
        << "\nsecret = " << keys.secret_key << "\n";
    umask(old);
    if (!out) return UnavailableError("cannot write key file '" + path + "'");
  }
  return Status::Ok();
}

StatusOr<CurveKeyPair> ReadCurveKeyFile(const std::string& path) {
  std::ifstream in(path);
  if (!in) return NotFoundError("cannot read CURVE key file '" + path + "'");
  CurveKeyPair keys;
  std::string line;
  while (std::getline(in, line)) {
    const size_t eq = line.find('=');
    if (line.empty() || line[0] == '#' || eq == std::string::npos) continue;
    const std::string key = Trim(line.substr(0, eq)), value = Trim(line.substr(eq + 1));
    if (key == "public") keys.public_key = value;
    else if (key == "secret") keys.secret_key = value;
  }
  if (!IsZ85Key(keys.public_key) || !IsZ85Key(keys.secret_key))
    return InvalidArgumentError("CURVE key file '" + path +
                                "' needs 'public = KEY' and 'secret = KEY' lines with 40-character Z85 keys");
  return keys;
}

StatusOr<std::set<std::string>> ReadAllowList(const std::string& path) {
  std::ifstream in(path);
  if (!in) return NotFoundError("cannot read the client allow-list '" + path + "'");
  std::set<std::string> keys;
  std::string line;
  int n = 0;
  while (std::getline(in, line)) {
    ++n;
    // Z85 keys may contain '#' and '=': comments are whole lines, and "public = KEY" is recognised by
    // its prefix.
    line = Trim(line);
    if (line.empty() || line[0] == '#') continue;
    if (line.rfind("secret", 0) == 0 && line.size() > 40) continue;  // a key file's secret line is never a client key
    if (line.rfind("public", 0) == 0 && line.size() > 40) line = Trim(Trim(line.substr(6)).substr(1));
    if (!IsZ85Key(line))
      return InvalidArgumentError(path + ":" + std::to_string(n) + ": not a 40-character Z85 public key");
    keys.insert(line);
  }
  return keys;
}

bool HandleZapRequest(zmq::socket_t& zap, const std::set<std::string>& allowed, std::string* client_key) {
  client_key->clear();
  std::vector<zmq::message_t> request;
  for (;;) {
    zmq::message_t part;
    if (!zap.recv(part, zmq::recv_flags::dontwait)) return false;
    const bool more = part.more();
    request.push_back(std::move(part));
    if (!more) break;
  }
  // version, request id, domain, address, routing id, mechanism, credentials...
  bool ok = false;
  if (request.size() >= 7 && request[5].to_string() == "CURVE" && request[6].size() == 32) {
    char z85[41];
    zmq_z85_encode(z85, static_cast<const uint8_t*>(request[6].data()), 32);
    *client_key = z85;
    ok = allowed.count(*client_key) > 0;
  }
  const std::string request_id = request.size() >= 2 ? request[1].to_string() : "";
  zap.send(zmq::buffer(std::string("1.0")), zmq::send_flags::sndmore);
  zap.send(zmq::buffer(request_id), zmq::send_flags::sndmore);
  zap.send(zmq::buffer(std::string(ok ? "200" : "400")), zmq::send_flags::sndmore);
  zap.send(zmq::buffer(std::string(ok ? "OK" : "client key not allowed")), zmq::send_flags::sndmore);
  zap.send(zmq::buffer(ok ? *client_key : std::string()), zmq::send_flags::sndmore);
  zap.send(zmq::buffer(std::string()), zmq::send_flags::none);
  return ok;
}

bool IsLoopbackEndpoint(const std::string& endpoint) {
  if (endpoint.rfind("ipc://", 0) == 0 || endpoint.rfind("inproc://", 0) == 0) return true;
  for (const char* local : {"tcp://127.", "tcp://localhost:", "tcp://[::1]:", "tcp://lo:"})
    if (endpoint.rfind(local, 0) == 0) return true;
  return false;
}

}  // namespace prism::server
