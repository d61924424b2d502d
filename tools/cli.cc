#include "tools/cli.h"

#include <iostream>
#include <map>
#include <memory>
#include <sstream>

namespace prism::cli {
namespace {

// CLI11's layout with the tool's own first line and usage lines.
class Formatter : public CLI::Formatter {
 public:
  explicit Formatter(std::vector<std::string> usage) : usage_(std::move(usage)) {
    column_width(32);
    label("Positionals", "arguments");
  }

  // " NAME=default": the value's name without CLI11's validator descriptions, which it appends after a
  // ':' (the help text states ranges; value names hold no ':').
  std::string make_option_opts(const CLI::Option* opt) const override {
    if (opt->get_type_size() == 0) return "";
    std::string type = opt->get_type_name();
    type = type.substr(0, type.find(':'));
    std::string out = type.empty() ? "" : " " + type;
    const std::string& default_value = opt->get_default_str();
    if (!default_value.empty() && default_value != "[]") out += "=" + default_value;
    return out;
  }

  std::string make_help(const CLI::App* app, std::string name, CLI::AppFormatMode mode) const override {
    if (mode == CLI::AppFormatMode::Sub) return CLI::Formatter::make_help(app, name, mode);
    std::ostringstream out;
    out << name << ": " << app->get_description() << "\n\n";
    for (size_t i = 0; i < usage_.size(); ++i) out << (i == 0 ? "usage: " : "       ") << usage_[i] << "\n";
    out << make_positionals(app) << make_groups(app, mode) << make_subcommands(app, mode);
    const std::string footer = app->get_footer();
    if (!footer.empty()) out << "\n" << footer << "\n";
    // CLI11 puts a blank line after each group but the last, which may be a hidden one.
    std::string text = out.str();
    for (size_t at; (at = text.find("\n\n\n")) != std::string::npos;) text.erase(at, 1);
    return text;
  }

 private:
  std::vector<std::string> usage_;
};

std::string Message(const CLI::ParseError& e) {
  const std::string m = e.what();
  if (dynamic_cast<const CLI::ExtrasError*>(&e) != nullptr) {
    const size_t colon = m.find(": ");
    return "unknown argument '" + (colon == std::string::npos ? m : m.substr(colon + 2)) + "'";
  }
  return m;
}

}  // namespace

void Setup(CLI::App* app, const std::string& purpose, const std::vector<std::string>& usage, const std::string& notes) {
  app->description(purpose);
  app->footer(notes);
  app->formatter(std::make_shared<Formatter>(usage));
  if (app->get_parent() != nullptr) app->group("commands");
  // An option given twice takes its last value, as the tools' own parsers did.
  app->option_defaults()->group("options")->multi_option_policy(CLI::MultiOptionPolicy::TakeLast);
  app->set_help_flag("-h,--help", "print this help and exit");
  app->option_defaults()->always_capture_default();
}

int Parse(CLI::App* app, int argc, char** argv, int usage_exit) {
  try {
    app->parse(argc, argv);
    return kContinue;
  } catch (const CLI::CallForHelp&) {
    std::cout << app->help();
    return 0;
  } catch (const CLI::CallForAllHelp&) {
    std::cout << app->help("", CLI::AppFormatMode::All);
    return 0;
  } catch (const CLI::ParseError& e) {
    std::string name = app->get_name();
    for (const CLI::App* sub = app; !sub->get_subcommands().empty();) {
      sub = sub->get_subcommands().front();
      name += " " + sub->get_name();
    }
    // An argument CLI11 could not place explains more than what it missed because of it (a mistyped
    // subcommand is reported as "A subcommand is required").
    const std::vector<std::string> extra = app->remaining(/*recurse=*/true);
    const std::string message = extra.empty() ? Message(e) : "unknown argument '" + extra.front() + "'";
    std::cerr << name << ": " << message << " (see --help)\n";
    return usage_exit;
  }
}

std::vector<std::pair<const CLI::Option*, std::string>> InCommandLineOrder(const CLI::App& app) {
  std::map<const CLI::Option*, size_t> seen;
  std::vector<std::pair<const CLI::Option*, std::string>> out;
  for (const CLI::Option* option : app.parse_order()) {
    const std::vector<std::string>& results = option->results();
    const size_t k = seen[option]++;
    out.emplace_back(option, k < results.size() ? results[k] : std::string());
  }
  return out;
}

}  // namespace prism::cli
