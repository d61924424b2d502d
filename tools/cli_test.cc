#include "tools/cli.h"

#include <string>
#include <vector>

#include <gtest/gtest.h>

namespace prism {
namespace {

// argv for CLI11 from strings (argv[0] is the program).
struct Argv {
  explicit Argv(std::vector<std::string> args) : args_(std::move(args)) {
    for (std::string& a : args_) pointers_.push_back(a.data());
  }
  int argc() { return static_cast<int>(pointers_.size()); }
  char** argv() { return pointers_.data(); }

 private:
  std::vector<std::string> args_;
  std::vector<char*> pointers_;
};

TEST(CliTest, ValuesComeBackInCommandLineOrderAndTheLastOneWins) {
  CLI::App app{"", "tool"};
  cli::Setup(&app, "a tool", {"tool [options]"});
  int n = 1;
  app.add_option("--n", n, "a number");
  CLI::Option* set = app.add_option("--set", "KEY=VALUE");
  CLI::Option* off = app.add_flag("--off", "a switch");
  Argv a({"tool", "--set", "a=1", "--n", "2", "--off", "--set", "b=2", "--n", "5"});
  ASSERT_EQ(cli::Parse(&app, a.argc(), a.argv()), cli::kContinue);
  EXPECT_EQ(n, 5);
  std::vector<std::string> order;
  for (const auto& [option, value] : cli::InCommandLineOrder(app)) {
    if (option == set) order.push_back("set " + value);
    if (option == off) order.push_back("off");
  }
  EXPECT_EQ(order, (std::vector<std::string>{"set a=1", "off", "set b=2"}));
}

TEST(CliTest, HelpShowsPurposeUsageDefaultsAndNotesAndErrorsExitWithTheUsageStatus) {
  CLI::App app{"", "tool"};
  cli::Setup(&app, "does one thing", {"tool --in FILE [options]", "tool --list"}, "Notes at the end.");
  int frames = 300;
  std::string in;
  app.add_option("--frames", frames, "frames to render")->type_name("N")->check(CLI::Range(2, 100));
  app.add_option("--in", in, "input")->type_name("FILE");
  const std::string help = app.help();
  EXPECT_EQ(help.rfind("tool: does one thing\n\nusage: tool --in FILE [options]\n       tool --list\n", 0), 0u) << help;
  EXPECT_NE(help.find("--frames N=300"), std::string::npos) << help;
  EXPECT_NE(help.find("Notes at the end."), std::string::npos) << help;

  Argv bad({"tool", "--frames", "1"});
  EXPECT_EQ(cli::Parse(&app, bad.argc(), bad.argv(), /*usage_exit=*/7), 7);
  CLI::App app2{"", "tool"};
  cli::Setup(&app2, "does one thing", {"tool"});
  Argv unknown({"tool", "--bogus"});
  testing::internal::CaptureStderr();
  EXPECT_EQ(cli::Parse(&app2, unknown.argc(), unknown.argv()), 2);
  EXPECT_EQ(testing::internal::GetCapturedStderr(), "tool: unknown argument '--bogus' (see --help)\n");
  CLI::App app3{"", "tool"};
  cli::Setup(&app3, "does one thing", {"tool"});
  Argv help_arg({"tool", "--help"});
  testing::internal::CaptureStdout();
  EXPECT_EQ(cli::Parse(&app3, help_arg.argc(), help_arg.argv()), 0);
  EXPECT_EQ(testing::internal::GetCapturedStdout().rfind("tool: does one thing", 0), 0u);
}

}  // namespace
}  // namespace prism
