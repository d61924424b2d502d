// libFuzzer target: the server boundary. Each input is one multipart message [routing id][Envelope]
// [payload?] (framed as in fuzz/fuzz_input.h) handed to a real in-process prism-server's handlers:
// validation, OpenSession (rig checks, admission, resume lookups), Frame, ChunkCredits, Close.
#include <unistd.h>

#include <cstdint>
#include <cstdlib>
#include <filesystem>
#include <memory>
#include <string>
#include <vector>

#include "core/util/logging.h"
#include "fuzz/fuzz_input.h"
#include "server/server.h"

namespace {

prism::server::Server* TheServer() {
  static prism::server::Server* server = [] {
    prism::SetMinLogLevel(prism::LogLevel::kError);
    prism::server::ServerOptions options;
    options.bind =
        "ipc://" + (std::filesystem::temp_directory_path() / ("prism_fuzz_" + std::to_string(getpid()))).string();
    options.data_dir =
        (std::filesystem::temp_directory_path() / ("prism_fuzz_data_" + std::to_string(getpid()))).string();
    options.metrics_bind = "off";
    options.max_sessions = 2;  // a few real sessions, then admission refusals
    options.threads = 1;
    auto created = prism::server::Server::Create(options);
    if (!created.ok()) std::abort();
    return created->release();
  }();
  return server;
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  std::vector<std::string> parts = prism::fuzz::SplitParts(data, size);
  if (parts.empty()) return 0;
  TheServer()->HandleMessageForFuzzing(parts);
  return 0;
}
