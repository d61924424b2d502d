// CURVE on a real prism-server: keys from `prism-server keygen`, an allow-list of client public keys;
// an allowed client streams, a client with an unknown key, a wrong server key or no keys at all is
// refused with kUnauthenticated (a readable error, at once, not a timeout). Plain TCP on a
// non-loopback address is logged as a warning.
#include <prism/client/client.h>
#include <unistd.h>

#include <chrono>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <string>

#include <gtest/gtest.h>

#include "tests/client_rig.h"
#include "tests/server_process.h"
#include "tests/test_process.h"

namespace prism {
namespace {
namespace fs = std::filesystem;
using test::Bin;
using test::Execute;
using test::ProcessResult;
using test::ServerProcess;
using test::SmallRig;

std::string Key(const std::string& file, const std::string& which) {
  std::ifstream in(file);
  std::string line;
  while (std::getline(in, line))
    if (line.rfind(which + " = ", 0) == 0) return line.substr(which.size() + 3);
  return "";
}

class ServerCurveTest : public ::testing::Test {
 protected:
  void SetUp() override {
    dir_ = fs::temp_directory_path() / ("prism_server_curve_test_" + std::to_string(getpid()) + "_" +
                                        ::testing::UnitTest::GetInstance()->current_test_info()->name());
    fs::remove_all(dir_);
    fs::create_directories(dir_);
  }
  void TearDown() override {
    if (!HasFailure()) fs::remove_all(dir_);
  }
  std::string P(const std::string& name) const { return (dir_ / name).string(); }
  fs::path dir_;
};

TEST_F(ServerCurveTest, AllowedKeyStreamsAndOthersAreRefusedWithAnAuthError) {
  // Many key pairs, so keys with Z85's '#' and '=' characters turn up in the files.
  for (const char* name :
       {"server.key", "alice.key", "mallory.key", "other_server.key", "k1", "k2", "k3", "k4", "k5", "k6", "k7", "k8"}) {
    const ProcessResult r = Execute(Bin("prism-server") + " keygen --out " + P(name));
    ASSERT_EQ(r.exit_code, 0) << r.out;
    ASSERT_EQ(r.out.size(), 41u) << r.out;  // the public key and a newline
    EXPECT_EQ((fs::status(P(name)).permissions() & fs::perms::others_read), fs::perms::none);
  }
  {
    std::ofstream allowed(P("allowed.txt"));
    allowed << "# alice\n" << Key(P("alice.key"), "public") << "\n\n";
    for (const char* k : {"k1", "k2", "k3", "k4", "k5", "k6", "k7", "k8"})
      allowed << "public = " << Key(P(k), "public") << "\n";
  }
  ServerProcess server(P("data"), {"--curve-keys", P("server.key"), "--allowed-clients", P("allowed.txt")},
                       P("server.log"));
  ASSERT_TRUE(server.ok());
  client::SessionOptions options;
  options.timeout_ms = 10000;
  options.server_public_key = Key(P("server.key"), "public");
  auto open_as = [&](const std::string& key_file, const std::string& server_key, client::Status* status) {
    client::SessionOptions o = options;
    o.server_public_key = server_key;
    if (!key_file.empty()) {
      o.client_public_key = Key(P(key_file), "public");
      o.client_secret_key = Key(P(key_file), "secret");
    }
    std::unique_ptr<client::Session> session;
    const auto t0 = std::chrono::steady_clock::now();
    *status = client::Session::Open(server.endpoint(), SmallRig(), o, &session);
    return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  };
  client::Status st;
  open_as("alice.key", options.server_public_key, &st);
  EXPECT_TRUE(st.ok()) << st.ToString();
  // An unknown client key: refused by the ZAP handler, reported at once.
  double seconds = open_as("mallory.key", options.server_public_key, &st);
  EXPECT_EQ(st.code, client::Code::kUnauthenticated) << st.ToString();
  EXPECT_LT(seconds, 3.0);
  std::cout << "unknown key: " << st.ToString() << " after " << seconds << " s\n";
  // The right client key but a wrong server key: the handshake fails.
  seconds = open_as("alice.key", Key(P("other_server.key"), "public"), &st);
  EXPECT_EQ(st.code, client::Code::kUnauthenticated) << st.ToString();
  EXPECT_LT(seconds, 3.0);
  std::cout << "wrong server key: " << st.ToString() << " after " << seconds << " s\n";
  // No keys at all (plain client against a CURVE server).
  seconds = open_as("", "", &st);
  EXPECT_FALSE(st.ok());
  std::cout << "plain client: " << st.ToString() << " after " << seconds << " s\n";
  EXPECT_EQ(server.Stop(), 0);
  std::ifstream log(P("server.log"));
  std::stringstream text;
  text << log.rdbuf();
  EXPECT_NE(text.str().find("event=auth_refused client_key=" + Key(P("mallory.key"), "public")), std::string::npos);
  EXPECT_EQ(text.str().find("unencrypted_listener"), std::string::npos);
}

TEST_F(ServerCurveTest, PlainTcpOnANonLoopbackAddressIsLoggedAsAWarning) {
  ServerProcess server(P("data"), {"--bind", "tcp://0.0.0.0:*"}, P("server.log"));
  ASSERT_TRUE(server.ok());
  EXPECT_EQ(server.Stop(), 0);
  std::ifstream log(P("server.log"));
  std::stringstream text;
  text << log.rdbuf();
  EXPECT_NE(text.str().find(" WARN "), std::string::npos) << text.str();
  EXPECT_NE(text.str().find("event=unencrypted_listener"), std::string::npos) << text.str();
  // A CURVE key file without an allow-list is a configuration error, named.
  const ProcessResult r = Execute(Bin("prism-server") + " --data-dir " + P("data") + " --curve-keys /nonexistent");
  EXPECT_EQ(r.exit_code, 2);
  EXPECT_NE(r.out.find("allowed_clients"), std::string::npos) << r.out;
}

}  // namespace
}  // namespace prism
