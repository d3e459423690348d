// runner.cpp -- registry and main() of the host test runner (see runner.h).
#include "runner.h"

#include <cstdio>
#include <vector>

namespace testing {
namespace {
struct Case {
  const char* name;
  void (*fn)();
};
std::vector<Case>& cases() {
  static std::vector<Case> c;
  return c;
}
int g_failures_in_case = 0;
std::string g_vectors_path;
}  // namespace

Registrar::Registrar(const char* name, void (*fn)()) { cases().push_back(Case{name, fn}); }

void report_failure(const char* file, int line, const std::string& what) {
  ++g_failures_in_case;
  std::fprintf(stderr, "  %s:%d: %s\n", file, line, what.c_str());
}

const std::string& vectors_path() { return g_vectors_path; }

}  // namespace testing

int main(int argc, char** argv) {
  using namespace testing;
  if (argc > 1) g_vectors_path = argv[1];
  const char* only = argc > 2 ? argv[2] : nullptr;
  int passed = 0, failed = 0;
  for (const Case& c : cases()) {
    if (only && std::string(c.name).find(only) == std::string::npos) continue;
    g_failures_in_case = 0;
    c.fn();
    if (g_failures_in_case == 0) {
      ++passed;
    } else {
      ++failed;
      std::fprintf(stderr, "FAIL %s\n", c.name);
    }
  }
  std::printf("%d passed, %d failed\n", passed, failed);
  return failed == 0 && passed > 0 ? 0 : 1;
}
