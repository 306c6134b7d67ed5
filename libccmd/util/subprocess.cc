#include "libccmd/util/subprocess.h"

#include <fcntl.h>
#include <poll.h>
#include <signal.h>
#include <sys/resource.h>
#include <sys/wait.h>
#include <unistd.h>

#include <cerrno>
#include <cstring>
#include <fstream>
#include <sstream>
#include <thread>

#include "libccmd/util/timer.h"

namespace ccmd {

struct Subprocess::Drainer {
  std::thread thread;
};

StatusOr<Subprocess> Subprocess::Start(const std::vector<std::string>& argv,
                                       const std::string& stdout_path,
                                       const std::string& stderr_path, bool pipe_stdout) {
  if (argv.empty()) return InvalidArgument("no program to start");
  int pipe_fds[2] = {-1, -1};
  if (pipe_stdout && ::pipe2(pipe_fds, O_CLOEXEC) != 0)
    return IoError(std::string("pipe: ") + std::strerror(errno));
  // Files are opened before fork so that errors are reported here.
  int out_fd = -1, err_fd = -1;
  if (!pipe_stdout && !stdout_path.empty()) {
    out_fd = ::open(stdout_path.c_str(), O_WRONLY | O_CREAT | O_TRUNC | O_CLOEXEC, 0644);
    if (out_fd < 0) return IoError("cannot open " + stdout_path + ": " + std::strerror(errno));
  }
  if (!stderr_path.empty()) {
    err_fd = ::open(stderr_path.c_str(), O_WRONLY | O_CREAT | O_TRUNC | O_CLOEXEC, 0644);
    if (err_fd < 0) {
      if (out_fd >= 0) ::close(out_fd);
      return IoError("cannot open " + stderr_path + ": " + std::strerror(errno));
    }
  }
  std::vector<char*> args;
  for (const std::string& a : argv) args.push_back(const_cast<char*>(a.c_str()));
  args.push_back(nullptr);
  const pid_t pid = ::fork();
  if (pid < 0) return IoError(std::string("fork: ") + std::strerror(errno));
  if (pid == 0) {
    // Child: only async-signal-safe calls until exec.
    if (pipe_stdout) ::dup2(pipe_fds[1], 1);
    if (out_fd >= 0) ::dup2(out_fd, 1);
    if (err_fd >= 0) ::dup2(err_fd, 2);
    ::execv(args[0], args.data());
    static const char msg[] = "exec failed\n";
    (void)!::write(2, msg, sizeof(msg) - 1);
    ::_exit(127);
  }
  if (out_fd >= 0) ::close(out_fd);
  if (err_fd >= 0) ::close(err_fd);
  Subprocess p;
  p.pid_ = pid;
  if (pipe_stdout) {
    ::close(pipe_fds[1]);
    p.stdout_fd_ = pipe_fds[0];
  }
  return p;
}

Subprocess::Subprocess(Subprocess&& o) noexcept { *this = std::move(o); }

Subprocess& Subprocess::operator=(Subprocess&& o) noexcept {
  std::swap(pid_, o.pid_);
  std::swap(stdout_fd_, o.stdout_fd_);
  std::swap(buffered_, o.buffered_);
  std::swap(exited_, o.exited_);
  std::swap(result_, o.result_);
  std::swap(drainer_, o.drainer_);
  return *this;
}

Subprocess::~Subprocess() {
  if (pid_ > 0 && !exited_) {
    ::kill(pid_, SIGKILL);
    Wait();
  }
  if (drainer_) {
    if (drainer_->thread.joinable()) drainer_->thread.join();
    delete drainer_;
  } else if (stdout_fd_ >= 0) {
    ::close(stdout_fd_);
  }
}

StatusOr<std::string> Subprocess::ReadLine(double timeout_s) {
  const double deadline = MonotonicSeconds() + timeout_s;
  while (true) {
    const auto newline = buffered_.find('\n');
    if (newline != std::string::npos) {
      std::string line = buffered_.substr(0, newline);
      buffered_.erase(0, newline + 1);
      return line;
    }
    if (stdout_fd_ < 0) return EndOfStream("no stdout pipe");
    const double left = deadline - MonotonicSeconds();
    if (left <= 0) return Timeout("no line from the child within the time-out");
    pollfd p{stdout_fd_, POLLIN, 0};
    const int ready = ::poll(&p, 1, static_cast<int>(left * 1000) + 1);
    if (ready < 0 && errno != EINTR) return IoError(std::string("poll: ") + std::strerror(errno));
    if (ready <= 0) continue;
    char chunk[4096];
    const ssize_t n = ::read(stdout_fd_, chunk, sizeof(chunk));
    if (n == 0) return EndOfStream("the child closed its output");
    if (n < 0) {
      if (errno == EINTR) continue;
      return IoError(std::string("read: ") + std::strerror(errno));
    }
    buffered_.append(chunk, static_cast<std::size_t>(n));
  }
}

void Subprocess::DrainStdoutTo(const std::string& path) {
  if (stdout_fd_ < 0 || drainer_) return;
  drainer_ = new Drainer;
  const int fd = stdout_fd_;
  std::string pending = buffered_;
  buffered_.clear();
  drainer_->thread = std::thread([fd, path, pending] {
    std::ofstream out(path, std::ios::app);
    out << pending;
    char chunk[4096];
    ssize_t n;
    while ((n = ::read(fd, chunk, sizeof(chunk))) != 0) {
      if (n < 0) {
        if (errno == EINTR) continue;
        break;
      }
      out.write(chunk, n);
      out.flush();
    }
    ::close(fd);
  });
}

void Subprocess::Reap(int status, const ::rusage& usage) {
  exited_ = true;
  result_.exit_code = WIFEXITED(status) ? WEXITSTATUS(status) : -1;
  result_.signal = WIFSIGNALED(status) ? WTERMSIG(status) : 0;
  result_.cpu_seconds = usage.ru_utime.tv_sec + usage.ru_utime.tv_usec * 1e-6 +
                        usage.ru_stime.tv_sec + usage.ru_stime.tv_usec * 1e-6;
  result_.max_rss_mb = usage.ru_maxrss / 1024.0;
}

bool Subprocess::Poll(ProcessResult* result) {
  if (exited_) {
    if (result) *result = result_;
    return true;
  }
  if (pid_ <= 0) return false;
  int status = 0;
  ::rusage usage{};
  const pid_t r = ::wait4(pid_, &status, WNOHANG, &usage);
  if (r != pid_) return false;
  Reap(status, usage);
  if (result) *result = result_;
  return true;
}

ProcessResult Subprocess::Wait() {
  if (exited_ || pid_ <= 0) return result_;
  int status = 0;
  ::rusage usage{};
  while (::wait4(pid_, &status, 0, &usage) < 0 && errno == EINTR) {
  }
  Reap(status, usage);
  return result_;
}

Status Subprocess::Signal(int signal) {
  if (pid_ <= 0 || exited_) return Status::Ok();
  if (::kill(pid_, signal) != 0) return IoError(std::string("kill: ") + std::strerror(errno));
  return Status::Ok();
}

double Subprocess::CpuSecondsSoFar() const {
  if (exited_) return result_.cpu_seconds;
  std::ifstream stat("/proc/" + std::to_string(pid_) + "/stat");
  std::string content((std::istreambuf_iterator<char>(stat)), std::istreambuf_iterator<char>());
  const auto close = content.rfind(')');
  if (close == std::string::npos) return 0;
  std::istringstream fields(content.substr(close + 2));
  std::string field;
  // Fields after the name: state(3) ... utime is field 14, stime 15 (1-based in proc(5)).
  long utime = 0, stime = 0;
  for (int i = 3; i <= 15 && fields >> field; ++i) {
    if (i == 14) utime = std::stol(field);
    if (i == 15) stime = std::stol(field);
  }
  return static_cast<double>(utime + stime) / ::sysconf(_SC_CLK_TCK);
}

}  // namespace ccmd
