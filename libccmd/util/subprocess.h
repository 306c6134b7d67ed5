#pragma once

// Child processes for tools that orchestrate the programs (ccmd_replay): spawn with arguments,
// stdout and stderr to files (or stdout to a pipe the caller reads), wait with the child's CPU
// time, signal. POSIX only.

#include <sys/resource.h>
#include <sys/types.h>

#include <string>
#include <vector>

#include "libccmd/util/status.h"

namespace ccmd {

struct ProcessResult {
  int exit_code = -1;      // -1 when killed by a signal
  int signal = 0;          // the signal that ended it, else 0
  double cpu_seconds = 0;  // user + system time of the child
  double max_rss_mb = 0;
};

class Subprocess {
 public:
  // Starts `argv[0]` (a path) with the arguments. stdout goes to `stdout_path` (or, if
  // `pipe_stdout`, to a pipe read with ReadLine), stderr to `stderr_path` ("" = inherit).
  static StatusOr<Subprocess> Start(const std::vector<std::string>& argv,
                                    const std::string& stdout_path, const std::string& stderr_path,
                                    bool pipe_stdout = false);
  Subprocess(Subprocess&& other) noexcept;
  Subprocess& operator=(Subprocess&& other) noexcept;
  ~Subprocess();  // kills (SIGKILL) and reaps a child still running

  pid_t pid() const { return pid_; }
  // One line from the piped stdout, waiting at most `timeout_s`. EndOfStream when the child
  // closed it, Timeout when nothing came.
  StatusOr<std::string> ReadLine(double timeout_s);
  // After the caller has what it needs from the pipe: a thread keeps draining it into
  // `path` so the child never blocks on a full pipe.
  void DrainStdoutTo(const std::string& path);
  // Non-blocking: true and the result if the child has exited.
  bool Poll(ProcessResult* result);
  // Blocks until the child exits.
  ProcessResult Wait();
  Status Signal(int signal);
  bool running() const { return pid_ > 0 && !exited_; }
  // CPU seconds used so far (from /proc while running; the final figure after exit).
  double CpuSecondsSoFar() const;

 private:
  Subprocess() = default;
  void Reap(int status, const ::rusage& usage);
  pid_t pid_ = -1;
  int stdout_fd_ = -1;
  std::string buffered_;
  bool exited_ = false;
  ProcessResult result_;
  struct Drainer;
  Drainer* drainer_ = nullptr;
};

}  // namespace ccmd
