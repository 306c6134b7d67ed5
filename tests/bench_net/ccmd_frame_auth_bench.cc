// ccmd_frame_auth_bench: what authenticating every frame (protocol version 2) costs per
// keyframe, against the rest of the transport's work on the same keyframe, measured in the
// same run on the same data.
//
//   ccmd_frame_auth_bench [--bytes 58800] [--keyframes 400] [--trials 9] [--json OUT]
//
// Per keyframe, in thread CPU time (median over trials; within a trial the phases alternate
// keyframe by keyframe, so machine load hits them alike):
//   server auth   checking the keyframe frame's tag, and tagging the Ack that answers it
//   agent auth    tagging the keyframe frame, and checking the Ack
//   server work   the transport's own work on the server without authentication: the
//                 stream decoder (header and payload CRC32C), the sequence number, the
//                 keyframe parse and re-serialisation for the traffic accounting, and the
//                 journal append (write(), no fdatasync)
//   HMAC-SHA256   for comparison: what a truncated HMAC-SHA256 over the same bytes (the other
//                 usual construction) would cost the server for the keyframe frame
// The ratio server auth / server work is the share authentication adds to the transport;
// the whole server (back-end included) reports its own share in its statistics
// ("authentication" in --stats, see docs/benchmarks/transport.md).

#include <time.h>
#include <unistd.h>

#include <CLI/CLI.hpp>
#include <algorithm>
#include <cstdio>
#include <cstdlib>
#include <string>
#include <vector>

#include "libccmd/net/frame_auth.h"
#include "libccmd/net/journal.h"
#include "libccmd/net/session_messages.h"
#include "libccmd/util/json.h"
#include "proto/frame.h"
#include "proto/messages.h"
#include "tests/bench_net/bench_keyframe.h"

namespace ccmd {
namespace {

using Bytes = std::vector<std::uint8_t>;

double ThreadCpu() {
  timespec t{};
  ::clock_gettime(CLOCK_THREAD_CPUTIME_ID, &t);
  return static_cast<double>(t.tv_sec) + 1e-9 * static_cast<double>(t.tv_nsec);
}

double Median(std::vector<double> v) {
  std::sort(v.begin(), v.end());
  return v[v.size() / 2];
}

SessionKeys Keys() {
  Nonce a{}, s{};
  a.fill(1);
  s.fill(2);
  static constexpr std::uint8_t kHello[] = {'a', ' ', 'h', 'e', 'l', 'l', 'o'};
  return DeriveSessionKeys("a benchmark deployment key", a, s, ByteSpan(kHello, sizeof(kHello)));
}

struct Phases {
  double server_auth = 0, agent_auth = 0, server_work = 0, hmac = 0;  // seconds over the trial
};

// One trial over every keyframe; the phases interleave per keyframe.
Phases Trial(const std::vector<Bytes>& keyframes, JournalWriter* journal) {
  const SessionKeys keys = Keys();
  SessionAuth agent(FrameRole::kAgent, keys, true), server(FrameRole::kServer, keys, true);
  FrameDecoder tagged_decoder, plain_decoder, ack_decoder;
  Phases p;
  Bytes tagged, plain, ack;
  std::vector<Frame> frames;
  for (std::size_t i = 0; i < keyframes.size(); ++i) {
    const std::uint64_t seq = i + 1;
    tagged.clear();
    double t = ThreadCpu();
    agent.AppendDataFrame(16, seq, keyframes[i], &tagged);
    p.agent_auth += ThreadCpu() - t;
    plain.clear();
    AppendDataFrame(16, seq, keyframes[i], &plain);

    // The server's own work on the untagged frame.
    frames.clear();
    t = ThreadCpu();
    plain_decoder.Feed(plain, &frames).IgnoreError();
    const DataEnvelope env = ParseDataEnvelope(frames.at(0).payload).value();
    const KeyframeMessage kf = ParseKeyframe(env.message).value();
    KeyframeSizeBreakdown parts;
    SerializeKeyframe(kf, &parts).value();
    journal->Append(16, env.seq, env.message).IgnoreError();
    p.server_work += ThreadCpu() - t;

    // Authentication on the server: the keyframe's tag, then the Ack's.
    frames.clear();
    tagged_decoder.Feed(tagged, &frames).IgnoreError();
    ack.clear();
    t = ThreadCpu();
    server.Verify(frames.at(0)).IgnoreError();
    server.AppendFrame(static_cast<std::uint8_t>(SessionType::kAck), SerializeAck({seq}), &ack);
    p.server_auth += ThreadCpu() - t;

    // The alternative: HMAC-SHA256 over counter, header and payload.
    t = ThreadCpu();
    Bytes mac_input(8, 0);
    mac_input.insert(mac_input.end(), tagged.begin(), tagged.end() - kFrameTagSize);
    [[maybe_unused]] const Mac mac = HmacSha256(keys.agent_to_server, mac_input);
    p.hmac += ThreadCpu() - t;

    // The agent checks the Ack.
    frames.clear();
    ack_decoder.Feed(ack, &frames).IgnoreError();
    t = ThreadCpu();
    agent.Verify(frames.at(0)).IgnoreError();
    p.agent_auth += ThreadCpu() - t;
  }
  // The agent's tag is the difference between tagged and untagged frame building.
  double untagged = 0;
  for (std::size_t i = 0; i < keyframes.size(); ++i) {
    plain.clear();
    const double t = ThreadCpu();
    AppendDataFrame(16, i + 1, keyframes[i], &plain);
    untagged += ThreadCpu() - t;
  }
  p.agent_auth -= untagged;
  return p;
}

}  // namespace
}  // namespace ccmd

int main(int argc, char** argv) {
  using namespace ccmd;
  CLI::App app{"Cost of frame authentication per keyframe, against the server's other work on it."};
  std::size_t bytes = 58800;
  int keyframes = 400, trials = 9;
  std::string json_path;
  app.add_option("--bytes", bytes, "Keyframe message size (the paper's average: 58.8 kB)")
      ->capture_default_str();
  app.add_option("--keyframes", keyframes, "Keyframes per trial")
      ->check(CLI::Range(1, 100000))
      ->capture_default_str();
  app.add_option("--trials", trials, "Trials (the median is reported)")
      ->check(CLI::Range(1, 1000))
      ->capture_default_str();
  app.add_option("--json", json_path, "Write the results as JSON");
  CLI11_PARSE(app, argc, argv);

  std::vector<std::vector<std::uint8_t>> messages;
  for (int k = 0; k < keyframes; ++k) messages.push_back(bench::MakeKeyframe(k % 16 + 1, bytes));
  char dir_template[] = "/tmp/ccmd_frame_auth_bench_XXXXXX";
  const std::string dir = ::mkdtemp(dir_template);
  std::vector<double> server_auth, agent_auth, server_work, hmac;
  for (int t = 0; t < trials; ++t) {
    const std::string path = dir + "/agent_00001.journal";
    ::unlink(path.c_str());
    auto journal = JournalWriter::Create(
        path, {AgentId(1), "bench", {525, 525, 319.5, 239.5, 640, 480, 5000}});
    if (!journal.ok()) {
      std::fprintf(stderr, "%s\n", journal.status().ToString().c_str());
      return 1;
    }
    const Phases p = Trial(messages, journal->get());
    server_auth.push_back(p.server_auth / keyframes);
    agent_auth.push_back(p.agent_auth / keyframes);
    server_work.push_back(p.server_work / keyframes);
    hmac.push_back(p.hmac / keyframes);
  }
  std::system(("rm -rf " + dir).c_str());
  const double sa = Median(server_auth), aa = Median(agent_auth), sw = Median(server_work),
               hm = Median(hmac);
  std::printf("keyframe of %zu bytes, %d keyframes x %d trials (median, thread CPU time)\n",
              messages[0].size(), keyframes, trials);
  std::printf("| per keyframe | us | ratio to server work |\n|---|---|---|\n");
  std::printf("| server work (decode, CRC, parse, accounting, journal write) | %.1f | 1 |\n",
              sw * 1e6);
  std::printf("| server auth (check the keyframe's tag, tag the ack) | %.1f | %.3f |\n", sa * 1e6,
              sa / sw);
  std::printf("| agent auth (tag the keyframe, check the ack) | %.1f | %.3f |\n", aa * 1e6,
              aa / sw);
  std::printf("| for comparison: HMAC-SHA256 of the keyframe frame | %.1f | %.3f |\n", hm * 1e6,
              hm / sw);
  std::printf("tag throughput on the server side: %.2f GB/s\n",
              static_cast<double>(messages[0].size()) / sa / 1e9);
  if (!json_path.empty()) {
    Json j = Json::MakeObject();
    j["keyframe_bytes"] = messages[0].size();
    j["server_work_us"] = sw * 1e6;
    j["server_auth_us"] = sa * 1e6;
    j["agent_auth_us"] = aa * 1e6;
    j["server_auth_ratio"] = sa / sw;
    j["hmac_sha256_us"] = hm * 1e6;
    if (Status s = WriteJsonFile(j, json_path); !s.ok()) {
      std::fprintf(stderr, "%s\n", s.ToString().c_str());
      return 1;
    }
  }
  return 0;
}
