#include "libccmd/util/subprocess.h"

#include <gtest/gtest.h>

#include <csignal>

#include "libccmd/util/file_util.h"
#include "tests/support/test_support.h"

namespace ccmd {
namespace {

TEST(SubprocessTest, ExitCodeOutputFileAndPipe) {
  testing::TempDir dir;
  auto p = Subprocess::Start({"/bin/sh", "-c", "echo hello; echo oops >&2; exit 3"},
                             dir.File("out"), dir.File("err"));
  ASSERT_TRUE(p.ok()) << p.status().ToString();
  const ProcessResult r = p->Wait();
  EXPECT_EQ(r.exit_code, 3);
  EXPECT_EQ(*ReadFileToString(dir.File("out")), "hello\n");
  EXPECT_EQ(*ReadFileToString(dir.File("err")), "oops\n");

  auto q = Subprocess::Start({"/bin/sh", "-c", "echo first; echo second; echo third"}, "", "",
                             /*pipe_stdout=*/true);
  ASSERT_TRUE(q.ok());
  EXPECT_EQ(*q->ReadLine(10), "first");
  q->DrainStdoutTo(dir.File("rest"));
  EXPECT_EQ(q->Wait().exit_code, 0);
  q = Subprocess::Start({"/bin/true"}, "", "");  // the drainer of the old one is joined here
  ASSERT_TRUE(q.ok());
  q->Wait();
  EXPECT_EQ(*ReadFileToString(dir.File("rest")), "second\nthird\n");
}

TEST(SubprocessTest, SignalEndsTheChildAndReadLineTimesOut) {
  auto p = Subprocess::Start({"/bin/sleep", "30"}, "", "", /*pipe_stdout=*/true);
  ASSERT_TRUE(p.ok());
  EXPECT_EQ(p->ReadLine(0.05).status().code(), StatusCode::kTimeout);
  ProcessResult r;
  EXPECT_FALSE(p->Poll(&r));
  ASSERT_TRUE(p->Signal(SIGTERM).ok());
  r = p->Wait();
  EXPECT_EQ(r.signal, SIGTERM);
  EXPECT_EQ(r.exit_code, -1);
}

TEST(SubprocessTest, CpuTimeIsCounted) {
  auto p = Subprocess::Start({"/bin/sh", "-c", "i=0; while [ $i -lt 200000 ]; do i=$((i+1)); done"},
                             "", "");
  ASSERT_TRUE(p.ok());
  const ProcessResult r = p->Wait();
  EXPECT_EQ(r.exit_code, 0);
  EXPECT_GT(r.cpu_seconds, 0.05);
}

TEST(SubprocessTest, MissingProgramFails) {
  testing::TempDir dir;
  auto p = Subprocess::Start({"/no/such/program"}, "", dir.File("err"));
  ASSERT_TRUE(p.ok());  // fork succeeded; exec fails in the child
  EXPECT_EQ(p->Wait().exit_code, 127);
}

}  // namespace
}  // namespace ccmd
