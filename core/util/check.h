// PRISM_CHECK: for bugs and broken invariants only. A failed check throws prism::CheckError, which a
// pipeline stage catches at its top level so that one session fails and the others go on.
// Never use it on client-supplied data: validate that with a Status (status.h).
#pragma once

#include <sstream>
#include <stdexcept>
#include <string>

namespace prism {

class CheckError : public std::logic_error {
 public:
  explicit CheckError(const std::string& what) : std::logic_error(what) {}
};

namespace internal {

// Collects the streamed message and throws from its destructor (the last thing the statement does).
class CheckFailure {
 public:
  CheckFailure(const char* file, int line, const char* condition) {
    stream_ << file << ":" << line << ": check failed: " << condition << ": ";
  }
  CheckFailure(const CheckFailure&) = delete;
  CheckFailure& operator=(const CheckFailure&) = delete;
  [[noreturn]] ~CheckFailure() noexcept(false) { throw CheckError(stream_.str()); }
  std::ostream& stream() { return stream_; }

 private:
  std::ostringstream stream_;
};

// Makes `cond ? (void)0 : Voidify() & stream` well-typed.
struct CheckVoidify {
  void operator&(std::ostream&) {}
};

}  // namespace internal
}  // namespace prism

#define PRISM_CHECK(condition) \
  (condition)                  \
      ? (void)0                \
      : ::prism::internal::CheckVoidify() & ::prism::internal::CheckFailure(__FILE__, __LINE__, #condition).stream()

#define PRISM_CHECK_EQ(a, b) PRISM_CHECK((a) == (b)) << #a " = " << (a) << ", " #b " = " << (b) << " "
#define PRISM_CHECK_LT(a, b) PRISM_CHECK((a) < (b)) << #a " = " << (a) << ", " #b " = " << (b) << " "
#define PRISM_CHECK_LE(a, b) PRISM_CHECK((a) <= (b)) << #a " = " << (a) << ", " #b " = " << (b) << " "
#define PRISM_CHECK_GT(a, b) PRISM_CHECK((a) > (b)) << #a " = " << (a) << ", " #b " = " << (b) << " "
#define PRISM_CHECK_GE(a, b) PRISM_CHECK((a) >= (b)) << #a " = " << (a) << ", " #b " = " << (b) << " "
