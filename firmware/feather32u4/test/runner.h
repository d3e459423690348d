// runner.h -- a tiny self-contained test runner for the host build of the firmware core.
//
// TEST(name) { CHECK(...); CHECK_EQ(a, b); } registers a test; main() (runner.cpp) runs them all
// and ends with "N passed, M failed". No external framework, nothing downloaded.
#ifndef STIPI_TEST_RUNNER_H
#define STIPI_TEST_RUNNER_H

#include <cstdint>
#include <sstream>
#include <string>

namespace testing {

struct Registrar {
  Registrar(const char* name, void (*fn)());
};

void report_failure(const char* file, int line, const std::string& what);
// Path of tests/vectors/protocol_vectors.txt (first command-line argument).
const std::string& vectors_path();

template <typename T>
std::string show(const T& v) {
  std::ostringstream os;
  os << +v;  // + prints uint8_t as a number
  return os.str();
}

}  // namespace testing

#define TEST(name)                                              \
  static void name();                                           \
  static ::testing::Registrar registrar_##name(#name, &name);   \
  static void name()

#define CHECK(cond)                                                                   \
  do {                                                                                \
    if (!(cond)) ::testing::report_failure(__FILE__, __LINE__, "CHECK(" #cond ")");   \
  } while (0)

#define CHECK_EQ(a, b)                                                                     \
  do {                                                                                     \
    const auto va_ = (a);                                                                  \
    const auto vb_ = (b);                                                                  \
    if (!(va_ == vb_))                                                                     \
      ::testing::report_failure(__FILE__, __LINE__,                                        \
                                "CHECK_EQ(" #a ", " #b "): " + ::testing::show(va_) +      \
                                    " != " + ::testing::show(vb_));                        \
  } while (0)

#endif
