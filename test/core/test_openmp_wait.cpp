// The OpenMP wait policy a program linking the core starts with (src/openmp_wait): libgomp's
// initializer reads a spin count of 30000 when the user set neither OMP_WAIT_POLICY nor GOMP_SPINCOUNT and the
// user's setting otherwise, as libgomp itself reports it (OMP_DISPLAY_ENV) in a fresh run of this
// program; the getenv that does it answers every other name as libc's getenv (the reference); a
// team of threads under it still forms and shares the work.
#include <gtest/gtest.h>

#include <omp.h>

#include <dlfcn.h>
#include <fcntl.h>
#include <spawn.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <cstdlib>
#include <string>
#include <vector>

extern char** environ;

namespace {

/// What libgomp read in its initializer when this program (which uses OpenMP, so libgomp is loaded)
/// starts with exactly `env`: the program runs again (listing its tests only) with
/// OMP_DISPLAY_ENV=VERBOSE, and libgomp's report on stderr is returned.
std::string libgompReport(std::vector<std::string> env) {
  env.push_back("OMP_DISPLAY_ENV=VERBOSE");
  std::vector<char*> envp;
  for (std::string& e : env) envp.push_back(e.data());
  envp.push_back(nullptr);
  int out[2];
  if (pipe(out) != 0) return "pipe failed";
  posix_spawn_file_actions_t actions;
  posix_spawn_file_actions_init(&actions);
  posix_spawn_file_actions_adddup2(&actions, out[1], STDERR_FILENO);
  posix_spawn_file_actions_addopen(&actions, STDOUT_FILENO, "/dev/null", O_WRONLY, 0);
  posix_spawn_file_actions_addclose(&actions, out[0]);
  std::string self = "/proc/self/exe", list = "--gtest_list_tests";
  char* argv[] = {self.data(), list.data(), nullptr};
  pid_t pid = 0;
  const int spawned = posix_spawn(&pid, "/proc/self/exe", &actions, nullptr, argv, envp.data());
  posix_spawn_file_actions_destroy(&actions);
  close(out[1]);
  std::string report;
  char buffer[4096];
  for (ssize_t n; (n = read(out[0], buffer, sizeof buffer)) > 0;) report.append(buffer, static_cast<size_t>(n));
  close(out[0]);
  if (spawned != 0) return "spawn failed";
  int status = 0;
  waitpid(pid, &status, 0);
  return report;
}

/// The value of `key` in libgomp's report ("  KEY = 'value'"), or "(absent)".
std::string reported(const std::string& report, const std::string& key) {
  const std::string start = "  " + key + " = '";
  const size_t at = report.find(start);
  if (at == std::string::npos) return "(absent)";
  const size_t from = at + start.size();
  return report.substr(from, report.find('\'', from) - from);
}

}  // namespace

TEST(OpenmpWait, LibgompSpinsBrieflyWhenTheUserSetNothing) {
  const std::string report = libgompReport({});
  EXPECT_EQ(reported(report, "GOMP_SPINCOUNT"), "30000") << report;
}

TEST(OpenmpWait, TheUsersOwnSettingIsKept) {
  std::string report = libgompReport({"OMP_WAIT_POLICY=active"});
  EXPECT_EQ(reported(report, "OMP_WAIT_POLICY"), "ACTIVE") << report;
  report = libgompReport({"GOMP_SPINCOUNT=1234"});
  EXPECT_EQ(reported(report, "GOMP_SPINCOUNT"), "1234") << report;
  report = libgompReport({"OMP_WAIT_POLICY=passive"});
  EXPECT_EQ(reported(report, "GOMP_SPINCOUNT"), "0") << report;
  report = libgompReport({"GOMP_SPINCOUNT=300000"});
  EXPECT_EQ(reported(report, "GOMP_SPINCOUNT"), "300000") << report;
}

TEST(OpenmpWait, GetenvAnswersAsLibcForEveryOtherName) {
  using Getenv = char* (*)(const char*);
  void* libc = dlopen("libc.so.6", RTLD_NOW | RTLD_NOLOAD);
  ASSERT_NE(libc, nullptr);
  const auto libc_getenv = reinterpret_cast<Getenv>(dlsym(libc, "getenv"));
  ASSERT_NE(libc_getenv, nullptr);
  // This program binds getenv to the library's, not to libc's.
  ASSERT_NE(reinterpret_cast<void*>(&getenv), reinterpret_cast<void*>(libc_getenv));

  ASSERT_EQ(setenv("BREAST_SIM_WAIT_TEST", "1", 1), 0);
  ASSERT_EQ(setenv("BREAST_SIM_WAIT_TEST_LONGER", "2", 1), 0);
  ASSERT_EQ(setenv("BREAST_SIM_WAIT_TEST_EMPTY", "", 1), 0);
  unsetenv("BREAST_SIM_WAIT_TEST_ABSENT");
  for (const char* name : {"BREAST_SIM_WAIT_TEST", "BREAST_SIM_WAIT_TEST_LONGER", "BREAST_SIM_WAIT_TEST_EMPTY",
                           "BREAST_SIM_WAIT_TEST_ABSENT", "BREAST_SIM_WAIT_TES", "BREAST_SIM_WAIT_TEST=1", "", "B", "PATH",
                           "OMP_WAIT_POLICY"}) {
    SCOPED_TRACE(name);
    EXPECT_EQ(getenv(name), libc_getenv(name));  // the same entry of the environment, or both none
  }
  unsetenv("BREAST_SIM_WAIT_TEST");
  EXPECT_EQ(getenv("BREAST_SIM_WAIT_TEST"), nullptr);

  // GOMP_SPINCOUNT: libc's answer when either variable is set, else "30000".
  const bool user_set = libc_getenv("OMP_WAIT_POLICY") || libc_getenv("GOMP_SPINCOUNT");
  if (user_set) EXPECT_EQ(getenv("GOMP_SPINCOUNT"), libc_getenv("GOMP_SPINCOUNT"));
  else EXPECT_STREQ(getenv("GOMP_SPINCOUNT"), "30000");
}

TEST(OpenmpWait, ATeamFormsAndSharesTheWork) {
  const int threads = std::max(2, omp_get_max_threads());
  std::vector<int> iterations(static_cast<size_t>(threads), 0);
  long long sum = 0;
#pragma omp parallel for num_threads(threads) schedule(static) reduction(+ : sum)
  for (int i = 1; i <= 100000; ++i) {
    sum += i;
    ++iterations[static_cast<size_t>(omp_get_thread_num())];
  }
  EXPECT_EQ(sum, 100000LL * 100001LL / 2);
  for (int t = 0; t < threads; ++t) EXPECT_EQ(iterations[static_cast<size_t>(t)], 100000 / threads + (t < 100000 % threads));
}
