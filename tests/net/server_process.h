#pragma once

// ccmd_server as a child process for tests: started with arguments, its port read from its
// "listening on" line, its stderr appended to a log file; killed and reaped on destruction.

#include <fcntl.h>
#include <poll.h>
#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <cstdint>
#include <string>
#include <vector>

#include "libccmd/net/socket.h"
#include "libccmd/util/timer.h"
#include "tests/support/test_support.h"

namespace ccmd::nettest {

// ccmd_server as a child process; its port is read from its first line of output.
class ServerProcess {
 public:
  bool Start(const std::vector<std::string>& args, const std::string& log_path) {
    std::vector<std::string> all = {testing::ProgramPath("ccmd_server")};
    all.insert(all.end(), args.begin(), args.end());
    std::vector<char*> argv;
    for (std::string& s : all) argv.push_back(s.data());
    argv.push_back(nullptr);
    int out[2];
    if (::pipe2(out, O_CLOEXEC) != 0) return false;
    const int log = ::open(log_path.c_str(), O_WRONLY | O_CREAT | O_APPEND | O_CLOEXEC, 0644);
    pid_ = ::fork();
    if (pid_ == 0) {
      ::dup2(out[1], 1);
      ::dup2(log, 2);
      ::execv(argv[0], argv.data());
      ::_exit(127);
    }
    ::close(out[1]);
    ::close(log);
    UniqueFd read_end(out[0]);
    std::string line;
    const double deadline = MonotonicSeconds() + 20;
    char c;
    while (MonotonicSeconds() < deadline) {
      pollfd p{read_end.get(), POLLIN, 0};
      ::poll(&p, 1, 1000);
      const ssize_t n = ::read(read_end.get(), &c, 1);
      if (n == 0) return false;  // exited
      if (n < 0) continue;
      if (c != '\n') {
        line.push_back(c);
        continue;
      }
      const std::size_t colon = line.rfind(':');
      if (line.find("listening on") != std::string::npos && colon != std::string::npos) {
        port_ = static_cast<std::uint16_t>(std::stoi(line.substr(colon + 1)));
        return true;
      }
      line.clear();
    }
    return false;
  }
  void Signal(int sig) { ::kill(pid_, sig); }
  // Exit code, or 128 + signal.
  int Wait() {
    int status = 0;
    ::waitpid(pid_, &status, 0);
    pid_ = -1;
    return WIFEXITED(status) ? WEXITSTATUS(status) : 128 + WTERMSIG(status);
  }
  ~ServerProcess() {
    if (pid_ > 0) {
      Signal(SIGKILL);
      Wait();
    }
  }
  std::uint16_t port() const { return port_; }

 private:
  pid_t pid_ = -1;
  std::uint16_t port_ = 0;
};

}  // namespace ccmd::nettest
