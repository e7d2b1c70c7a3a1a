/* How the OpenMP threads of every program that links the core wait, without the user setting anything.
 *
 * libgomp's default spins a waiting thread for up to 300,000 iterations (about 3 ms) before it
 * sleeps: beside another busy process a spinning thread holds the core its team-mate needs, and a
 * time step became 30x slower. Sleeping at once (OMP_WAIT_POLICY=passive) costs on an idle virtual
 * machine instead: every parallel region then wakes a sleeping CPU, and the main job took twice as
 * long as with a short spin. The default here is GOMP_SPINCOUNT=30000 (about 0.3 ms: one
 * iteration is a PAUSE instruction, 11 ns on the machine it was measured on), and the core runs one
 * thread per free core (include/breast_sim/core/thread_budget.h), so a spinning thread does not
 * share a core with other work (docs/load.md).
 *
 * libgomp reads OMP_WAIT_POLICY and GOMP_SPINCOUNT once, in its own initializer, before any
 * initializer or main() of ours runs; setenv() then is too late, and so is setenv() in a
 * DF_1_INITFIRST initializer, which runs before libc's own initializer resets the environment to the
 * one the process started with. This library therefore defines getenv(): linked ahead of libc, it is
 * the getenv every other library binds to, libgomp included, whatever order the initializers run in.
 * It answers as libc's getenv does, except that GOMP_SPINCOUNT reads "30000" when neither
 * OMP_WAIT_POLICY nor GOMP_SPINCOUNT is set: a user's own setting of either is kept. The environment
 * itself is not changed (child processes inherit it as it was).
 */
#include <stddef.h>
#include <string.h>

extern char** environ;

/* libc's getenv: the value of the first NAME=value entry of the environment. */
static char* lookup(const char* name) {
  if (environ == NULL || name[0] == '\0') return NULL;
  const size_t n = strlen(name);
  for (char** e = environ; *e != NULL; ++e)
    if (strncmp(*e, name, n) == 0 && (*e)[n] == '=') return *e + n + 1;
  return NULL;
}

__attribute__((visibility("default"))) char* getenv(const char* name) {
  char* value = lookup(name);
  if (value == NULL && strcmp(name, "GOMP_SPINCOUNT") == 0 && lookup("OMP_WAIT_POLICY") == NULL)
    return (char*)"30000";
  return value;
}
