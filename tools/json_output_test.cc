#include "tools/json_output.h"

#include <cmath>
#include <limits>
#include <string>

#include <gtest/gtest.h>

namespace prism {
namespace {

TEST(JsonTextTest, NoStringBreaksTheDocument) {
  const std::string nasty =
      std::string("a \"quoted\" back\\slash, new\nline, tab\t, bell\x07, ") + "bad UTF-8 \xff\xfe";
  const std::string text = JsonText(Json{{"message", nasty}, {"n", 3}});
  const Json back = Json::parse(text);
  EXPECT_EQ(back["n"], 3);
  const std::string message = back["message"];
  EXPECT_EQ(message.substr(0, 47), nasty.substr(0, 47)) << "everything up to the invalid bytes survives";
  EXPECT_NE(message.find("\xef\xbf\xbd"), std::string::npos) << "invalid UTF-8 becomes U+FFFD";
}

TEST(JsonTextTest, NonFiniteNumbersAreNullAndKeysKeepTheirOrder) {
  Json j;
  j["zeta"] = std::nan("");
  j["alpha"] = std::numeric_limits<double>::infinity();
  j["mid"] = 0.25;
  EXPECT_EQ(JsonText(j), "{\"zeta\":null,\"alpha\":null,\"mid\":0.25}\n");
  EXPECT_EQ(JsonText(Json{{"k", 1}}, 2), "{\n  \"k\": 1\n}\n") << "indented: \"key\": value, as tests and scripts read";
}

}  // namespace
}  // namespace prism
