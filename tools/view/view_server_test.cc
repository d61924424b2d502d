// The live view's chunk endpoint over real HTTP: a chunk the map holds, one a later chunk replaced
// (no content: the page skips it, no error in its console), one never received (not found).
#include "tools/view/view_server.h"

#include <unistd.h>

#include <filesystem>
#include <fstream>

#include <gtest/gtest.h>

#include "tools/http_get.h"

namespace prism {
namespace {

namespace fs = std::filesystem;

TEST(ViewServerTest, AChunkReplacedSinceThePageListedItIsNoContentNotAnError) {
  const fs::path web = fs::temp_directory_path() / ("prism_view_server_test_" + std::to_string(::getpid()));
  fs::create_directories(web);
  std::ofstream(web / "index.html") << "<!doctype html>";
  auto server = ViewServer::Start("127.0.0.1:0", web.string());
  ASSERT_TRUE(server.ok()) << server.status().ToString();
  ViewServer& view = **server;
  view.AddChunkBytes(1, 1, 3, false, {1, 2, 3});
  view.AddChunkBytes(2, 2, 3, false, {4, 5, 6});
  HttpResponse r = FetchHttp(view.url() + "api/chunks/1.drc", 5000);
  EXPECT_EQ(r.status, 200) << r.error;
  EXPECT_EQ(r.body, std::string("\x01\x02\x03", 3));

  view.AddChunkBytes(3, 2, 4, true, {7, 8, 9, 10});  // replaces the map: 1 and 2 are void
  r = FetchHttp(view.url() + "api/chunks/1.drc", 5000);
  EXPECT_EQ(r.status, 204) << r.error;
  EXPECT_TRUE(r.body.empty());
  r = FetchHttp(view.url() + "api/chunks/3.drc", 5000);
  EXPECT_EQ(r.status, 200) << r.error;
  EXPECT_EQ(r.body.size(), 4u);
  r = FetchHttp(view.url() + "api/chunks/9.drc", 5000);
  EXPECT_EQ(r.status, 404) << r.error;
  r = FetchHttp(view.url() + "api/state", 5000);
  EXPECT_EQ(r.status, 200) << r.error;
  EXPECT_NE(r.body.find("\"chunks_voided\":2"), std::string::npos) << r.body;
  fs::remove_all(web);
}

}  // namespace
}  // namespace prism
