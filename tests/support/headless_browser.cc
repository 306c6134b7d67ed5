#include "tests/support/headless_browser.h"

#include <fcntl.h>
#include <poll.h>
#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <cerrno>
#include <cstdlib>
#include <cstring>
#include <filesystem>

#include "libccmd/util/timer.h"

namespace ccmd::testing {

namespace {

bool OnPath(const std::string& program) {
  if (program.find('/') != std::string::npos) return ::access(program.c_str(), X_OK) == 0;
  const char* path = std::getenv("PATH");
  std::string dirs = path ? path : "/usr/bin:/bin";
  std::size_t start = 0;
  while (start <= dirs.size()) {
    const std::size_t end = std::min(dirs.find(':', start), dirs.size());
    if (::access((dirs.substr(start, end - start) + "/" + program).c_str(), X_OK) == 0) return true;
    start = end + 1;
  }
  return false;
}

}  // namespace

StatusOr<std::string> DecodeBase64(const std::string& text) {
  std::string out;
  unsigned value = 0;
  int bits = 0;
  for (char c : text) {
    int d;
    if (c >= 'A' && c <= 'Z') {
      d = c - 'A';
    } else if (c >= 'a' && c <= 'z') {
      d = c - 'a' + 26;
    } else if (c >= '0' && c <= '9') {
      d = c - '0' + 52;
    } else if (c == '+') {
      d = 62;
    } else if (c == '/') {
      d = 63;
    } else if (c == '=' || c == '\n' || c == '\r') {
      continue;
    } else {
      return InvalidArgument("base64: unexpected character");
    }
    value = (value << 6) | static_cast<unsigned>(d);
    bits += 6;
    if (bits >= 8) {
      bits -= 8;
      out.push_back(static_cast<char>((value >> bits) & 0xff));
    }
  }
  return out;
}

StatusOr<std::unique_ptr<HeadlessBrowser>> HeadlessBrowser::Launch(const BrowserOptions& options) {
  if (!OnPath(options.executable)) {
    return NotFound(options.executable +
                    " is not installed (scripts/setup.sh installs Debian's chromium)");
  }
  ::signal(SIGPIPE, SIG_IGN);  // a browser that died is an error to report, not a reason to die
  std::unique_ptr<HeadlessBrowser> browser(new HeadlessBrowser());
  browser->options_ = options;
  char profile[] = "/tmp/ccmd_chromium_XXXXXX";
  if (::mkdtemp(profile) == nullptr) return IoError("cannot make a browser profile folder");
  browser->profile_dir_ = profile;
  int commands[2], answers[2];
  if (::pipe2(commands, O_CLOEXEC) != 0 || ::pipe2(answers, O_CLOEXEC) != 0)
    return IoError("pipe failed");
  // Every flag keeps the browser quiet and local: no first-run work, no background network
  // (it would hammer a closed network), no GPU; WebGL uses the software renderer.
  std::vector<std::string> args = {
      options.executable,
      "--headless",
      "--no-sandbox",
      "--disable-gpu",
      "--disable-quic",
      "--no-first-run",
      "--disable-background-networking",
      "--disable-component-update",
      "--disable-sync",
      "--disable-dev-shm-usage",
      "--enable-unsafe-swiftshader",
      "--hide-scrollbars",
      "--mute-audio",
      "--user-data-dir=" + browser->profile_dir_,
      "--remote-debugging-pipe",
      "--window-size=" + std::to_string(options.width) + "," + std::to_string(options.height),
      "about:blank"};
  const pid_t pid = ::fork();
  if (pid < 0) return IoError("fork failed");
  if (pid == 0) {
    ::setpgid(0, 0);  // its helper processes go with it
    // Out of the way first: the pipe's own descriptors may be 3 or 4.
    const int in = ::fcntl(commands[0], F_DUPFD, 10), out = ::fcntl(answers[1], F_DUPFD, 10);
    ::dup2(in, 3);
    ::dup2(out, 4);
    const int log = options.log_path.empty()
                        ? ::open("/dev/null", O_WRONLY)
                        : ::open(options.log_path.c_str(), O_WRONLY | O_CREAT | O_TRUNC, 0644);
    if (log >= 0) {
      ::dup2(log, 1);
      ::dup2(log, 2);
    }
    std::vector<char*> argv;
    for (std::string& a : args) argv.push_back(a.data());
    argv.push_back(nullptr);
    ::execvp(argv[0], argv.data());
    ::_exit(127);
  }
  ::close(commands[0]);
  ::close(answers[1]);
  browser->pid_ = pid;
  browser->to_browser_ = commands[1];
  browser->from_browser_ = answers[0];
  // The first answer proves the browser is up.
  CCMD_RETURN_IF_ERROR(browser->Call("Browser.getVersion", Json::MakeObject(), -1, false).status());
  return browser;
}

HeadlessBrowser::~HeadlessBrowser() {
  if (pid_ > 0) {
    if (to_browser_ >= 0)
      Call("Browser.close", Json::MakeObject(), 10, false).status().IgnoreError();
    // The browser closes its end of the pipe when it exits; read until then (bounded).
    const double deadline = MonotonicSeconds() + 10;
    while (Read(deadline).ok()) {
    }
    int status = 0;
    if (::waitpid(pid_, &status, WNOHANG) == 0) {
      ::kill(-pid_, SIGKILL);  // its own process group: only what this launch started
      ::waitpid(pid_, &status, 0);
    }
  }
  if (to_browser_ >= 0) ::close(to_browser_);
  if (from_browser_ >= 0) ::close(from_browser_);
  std::error_code ec;
  if (!profile_dir_.empty()) std::filesystem::remove_all(profile_dir_, ec);
}

StatusOr<Json> HeadlessBrowser::Read(double deadline) {
  while (true) {
    const std::size_t end = buffer_.find('\0');
    if (end != std::string::npos) {
      const std::string text = buffer_.substr(0, end);
      buffer_.erase(0, end + 1);
      return Json::Parse(text);
    }
    const double left = deadline - MonotonicSeconds();
    if (left <= 0) return Timeout("no answer from the browser in time");
    pollfd p{from_browser_, POLLIN, 0};
    const int ready = ::poll(&p, 1, static_cast<int>(left * 1000) + 1);
    if (ready < 0 && errno == EINTR) continue;
    if (ready <= 0) continue;
    char chunk[1 << 16];
    const ssize_t n = ::read(from_browser_, chunk, sizeof(chunk));
    if (n < 0 && errno == EINTR) continue;
    if (n <= 0) return Unavailable("the browser closed its pipe (it exited)");
    buffer_.append(chunk, static_cast<std::size_t>(n));
  }
}

void HeadlessBrowser::NoteEvent(const Json& message) {
  const Json* method = message.Get("method");
  if (!method) return;
  const Json* params = message.Get("params");
  if (method->string() == "Runtime.consoleAPICalled" && params && params->Get("args")) {
    page_log_ += "console:";
    for (const Json& a : params->Get("args")->array()) {
      page_log_ += ' ';
      page_log_ += a.Get("value") ? a.Get("value")->Dump(-1) : a.Dump(-1);
    }
    page_log_ += "\n";
  } else if (method->string() == "Runtime.exceptionThrown" && params) {
    page_log_ += "exception: " + params->Dump(-1).substr(0, 2000) + "\n";
  }
  events_.push_back(message);
  if (events_.size() > 1000) events_.erase(events_.begin(), events_.begin() + 500);
}

StatusOr<Json> HeadlessBrowser::Call(const std::string& method, Json params, double timeout_s,
                                     bool page) {
  Json message;
  const int id = ++next_id_;
  message["id"] = id;
  message["method"] = method;
  message["params"] = std::move(params);
  if (page && !session_.empty()) message["sessionId"] = session_;
  const std::string text = message.Dump(-1) + std::string(1, '\0');
  std::size_t written = 0;
  while (written < text.size()) {
    const ssize_t n = ::write(to_browser_, text.data() + written, text.size() - written);
    if (n < 0 && errno == EINTR) continue;
    if (n <= 0) return Unavailable("cannot write to the browser");
    written += static_cast<std::size_t>(n);
  }
  const double deadline = MonotonicSeconds() + (timeout_s > 0 ? timeout_s : options_.timeout_s);
  while (true) {
    CCMD_ASSIGN_OR_RETURN(Json answer, Read(deadline));
    if (!answer.Get("id") || static_cast<int>(answer.Get("id")->number()) != id) {
      NoteEvent(answer);
      continue;
    }
    if (const Json* error = answer.Get("error")) return Internal(method + ": " + error->Dump(-1));
    const Json* result = answer.Get("result");
    return result ? *result : Json::MakeObject();
  }
}

Status HeadlessBrowser::Open(const std::string& url) {
  Json create;
  create["url"] = "about:blank";
  CCMD_ASSIGN_OR_RETURN(const Json target, Call("Target.createTarget", create, -1, false));
  Json attach;
  attach["targetId"] = target.Get("targetId") ? target.Get("targetId")->string() : "";
  attach["flatten"] = true;
  CCMD_ASSIGN_OR_RETURN(const Json session, Call("Target.attachToTarget", attach, -1, false));
  session_ = session.Get("sessionId") ? session.Get("sessionId")->string() : "";
  CCMD_RETURN_IF_ERROR(Call("Runtime.enable", Json::MakeObject()).status());
  CCMD_RETURN_IF_ERROR(Call("Page.enable", Json::MakeObject()).status());
  Json metrics;
  metrics["width"] = options_.width;
  metrics["height"] = options_.height;
  metrics["deviceScaleFactor"] = 1;
  metrics["mobile"] = false;
  CCMD_RETURN_IF_ERROR(Call("Emulation.setDeviceMetricsOverride", metrics).status());
  events_.clear();
  Json navigate;
  navigate["url"] = url;
  CCMD_ASSIGN_OR_RETURN(const Json navigated, Call("Page.navigate", navigate));
  if (const Json* error = navigated.Get("errorText"))
    return Unavailable("cannot open " + url + ": " + error->string());
  const double deadline = MonotonicSeconds() + options_.timeout_s;
  while (true) {
    for (const Json& e : events_) {
      if (e.Get("method") && e.Get("method")->string() == "Page.loadEventFired")
        return Status::Ok();
    }
    CCMD_ASSIGN_OR_RETURN(Json message, Read(deadline));
    NoteEvent(message);
  }
}

StatusOr<Json> HeadlessBrowser::Evaluate(const std::string& expression, double timeout_s) {
  Json params;
  params["expression"] = expression;
  params["awaitPromise"] = true;
  params["returnByValue"] = true;
  CCMD_ASSIGN_OR_RETURN(const Json result, Call("Runtime.evaluate", params, timeout_s));
  if (const Json* exception = result.Get("exceptionDetails")) {
    const Json* e = exception->Get("exception");
    return Internal("page: " + (e && e->Get("description") ? e->Get("description")->string()
                                                           : exception->Dump(-1)));
  }
  const Json* value = result.Get("result");
  return value && value->Get("value") ? *value->Get("value") : Json();
}

StatusOr<std::string> HeadlessBrowser::Screenshot() {
  Json params;
  params["format"] = "png";
  CCMD_ASSIGN_OR_RETURN(const Json shot, Call("Page.captureScreenshot", params));
  if (!shot.Get("data")) return Internal("no screenshot data");
  return DecodeBase64(shot.Get("data")->string());
}

}  // namespace ccmd::testing
