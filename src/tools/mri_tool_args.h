#pragma once
// Command-line reading shared by the MRI tools (breast_sim_make_mri, breast_sim_segment,
// breast_sim_supine_mri): options with values, --help, and errors that print the usage.
#include <iostream>
#include <stdexcept>
#include <string>

namespace breast_sim::tools {

/// Walks argv: `next()` gives the next option (false at the end), `value()` the value after it (an
/// error naming the option and showing the usage when there is none).
class Arguments {
 public:
  Arguments(int argc, char** argv, const char* usage) : argc_(argc), argv_(argv), usage_(usage) {}
  bool next() { return ++i_ < argc_ && (option_ = argv_[i_], true); }
  const std::string& option() const { return option_; }
  std::string value() {
    if (i_ + 1 >= argc_) throw std::invalid_argument("option " + option_ + " needs a value\n" + usage_);
    return argv_[++i_];
  }
  /// --help or -h: the usage is printed and the tool should exit with 0.
  bool help() const {
    if (option_ != "--help" && option_ != "-h") return false;
    std::cout << usage_;
    return true;
  }
  /// A word that is no option (a positional argument).
  bool positional() const { return !option_.empty() && option_[0] != '-'; }
  [[noreturn]] void unknown() const { throw std::invalid_argument("unknown option " + option_ + "\n" + usage_); }

 private:
  int argc_;
  char** argv_;
  const char* usage_;
  int i_ = 0;
  std::string option_;
};

}  // namespace breast_sim::tools
