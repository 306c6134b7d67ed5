// Stopping the programs as users do, with Ctrl-C: the first signal stops cleanly; once a
// program is stopping, another one ends it at once instead of leaving it waiting.

#include <gtest/gtest.h>
#include <signal.h>

#include <string>

#include "libccmd/net/socket.h"
#include "libccmd/util/file_util.h"
#include "libccmd/util/subprocess.h"
#include "tests/support/test_support.h"

namespace ccmd {
namespace {

using testing::ProgramPath;

// A loopback port nobody listens on.
std::uint16_t ClosedPort() {
  bool loopback;
  UniqueFd probe = ListenTcp(HostPort{"127.0.0.1", 0}, 1, &loopback).value();
  return LocalPort(probe.get()).value();
}

// Reads the process's stdout until a line holds `text`.
bool ReadUntil(Subprocess* process, const std::string& text) {
  while (true) {
    auto line = process->ReadLine(120);
    if (!line.ok()) return false;
    if (line->find(text) != std::string::npos) return true;
  }
}

// A server on a free loopback port, once it serves; its stderr in dir/server.err.
StatusOr<Subprocess> StartServer(const testing::TempDir& dir) {
  CCMD_ASSIGN_OR_RETURN(
      Subprocess server,
      Subprocess::Start({ProgramPath("ccmd_server"), "--listen", "127.0.0.1:0", "--journal",
                         dir.File("journal"), "--out", dir.File("out"), "--no-fsync", "--no-dense"},
                        "", dir.File("server.err"), /*pipe_stdout=*/true));
  if (!ReadUntil(&server, "listening on")) return Unavailable("ccmd_server did not start");
  return server;
}

// With its server gone, an agent at the end of its source waits for acknowledgements (up to
// --flush-timeout without progress). Ctrl-C there ends it at once, and says what is lost.
TEST(StopCliTest, CtrlCWhileTheAgentWaitsForTheServerEndsItAtOnce) {
  testing::TempDir dir;
  auto agent =
      Subprocess::Start({ProgramPath("ccmd_agent"), "--source", "synth:frames=20,seed=2", "--rate",
                         "max", "--server", "127.0.0.1:" + std::to_string(ClosedPort()), "--name",
                         "stopper", "--spill-dir", dir.File("spill"), "--flush-timeout", "60"},
                        "", dir.File("agent.err"), /*pipe_stdout=*/true);
  ASSERT_TRUE(agent.ok()) << agent.status().ToString();
  ASSERT_TRUE(ReadUntil(&*agent, "waiting for the server to acknowledge"));
  ASSERT_TRUE(agent->Signal(SIGINT).ok());
  const ProcessResult result = agent->Wait();
  EXPECT_EQ(result.exit_code, 128 + SIGINT);
  const std::string err = ReadFileToString(dir.File("agent.err")).value();
  EXPECT_NE(err.find("not acknowledged"), std::string::npos) << err;
}

// Two stop signals at once: the server does not write the results but ends, pointing at the
// journal that holds what it acknowledged. (Stopped while they are sent, so that both are
// pending when it wakes, whatever the machine's load.)
TEST(StopCliTest, ASecondStopSignalEndsTheServerAndPointsAtItsJournal) {
  testing::TempDir dir;
  auto server = StartServer(dir);
  ASSERT_TRUE(server.ok()) << server.status().ToString();
  ASSERT_EQ(kill(server->pid(), SIGSTOP), 0);
  ASSERT_TRUE(server->Signal(SIGINT).ok());
  ASSERT_TRUE(server->Signal(SIGTERM).ok());
  ASSERT_EQ(kill(server->pid(), SIGCONT), 0);
  const ProcessResult result = server->Wait();
  EXPECT_EQ(result.exit_code, 128 + SIGTERM);
  const std::string err = ReadFileToString(dir.File("server.err")).value();
  EXPECT_NE(err.find("--resume " + dir.File("journal")), std::string::npos) << err;
  EXPECT_FALSE(FileExists(dir.File("out/trajectory_fused.txt")));
}

// One signal stops the server cleanly: results written, exit status 0.
TEST(StopCliTest, OneStopSignalStopsTheServerCleanly) {
  testing::TempDir dir;
  auto server = StartServer(dir);
  ASSERT_TRUE(server.ok()) << server.status().ToString();
  ASSERT_TRUE(server->Signal(SIGTERM).ok());
  EXPECT_EQ(server->Wait().exit_code, 0);
  EXPECT_TRUE(FileExists(dir.File("out/trajectory_fused.txt")));
}

}  // namespace
}  // namespace ccmd
