// ccmd_attack: a bounded attack run against a ccmd_server process it starts itself, on
// loopback only. An honest agent sends keyframes throughout, through a man in the middle
// that forges acknowledgements and injects keyframes now and then; meanwhile clients
// written from PROTOCOL.md send garbage, absurd lengths and hellos, broken frames, wrong
// and replayed keys, messages before authentication, dribbled hellos and frames, idle
// connections and storms of connections, try to take over the honest agent's name, and
// the server is killed with SIGKILL and resumed with a smaller frame limit. A keyless
// phase fills every agent slot with squatters. At the end:
//   - every attack got the refusal PROTOCOL.md gives for it,
//   - the honest agent lost nothing: messages queued = acknowledged = journaled, in order,
//     byte for byte, no duplicate, and no other agent's data was journaled,
//   - the server's log stayed small (refusals are summarised).
//
//   ccmd_attack                                  the short form (ctest net_attack_short)
//   ccmd_attack --rounds 5 --storm 5000 --idle 200  the long form (docs/benchmarks/transport.md)
//
// Bounded: every attack has a count and every wait a time limit; exit status 0 when all
// checks hold, 1 otherwise (the failures are listed).

#include <signal.h>
#include <sys/socket.h>

#include <sys/stat.h>

#include <CLI/CLI.hpp>
#include <atomic>
#include <chrono>
#include <cmath>
#include <condition_variable>
#include <cstdio>
#include <fstream>
#include <functional>
#include <limits>
#include <map>
#include <memory>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include "libccmd/net/agent_link.h"
#include "libccmd/net/journal.h"
#include "libccmd/util/file_util.h"
#include "libccmd/util/logging.h"
#include "proto/crc32c.h"
#include "tests/net/net_test_util.h"
#include "tests/net/server_process.h"
#include "tests/net/tamper_proxy.h"
#include "tests/support/test_support.h"

namespace ccmd {
namespace {

using nettest::Bytes;
using nettest::RawClient;
using nettest::TestCamera;
using nettest::TestIdentity;
using nettest::WireFrame;

const std::string kKey = "ccmd attack run deployment key 0123";
const std::string kOtherKey = "a key that is not the deployment's";

struct Config {
  int rounds = 1;
  int storm = 200;
  int idle = 20;
  double seconds_limit = 600;
};

// Outcome per attack kind.
struct Tally {
  std::map<std::string, std::pair<int, int>> runs;  // kind -> (run, as expected)
  std::vector<std::string> failures;
  void Note(const std::string& kind, bool ok, const std::string& what = "") {
    auto& r = runs[kind];
    ++r.first;
    r.second += ok;
    if (!ok) failures.push_back(kind + ": " + what);
  }
};

// The honest agent's message i (the first 20 are large, to test resuming with a smaller
// frame limit; the rest small).
Bytes Honest(std::uint64_t i) {
  return nettest::SyntheticKeyframe(0, i, 40, i < 20 ? 100000 : 3000);
}

HelloMessage BaseHello(const std::string& name) {
  HelloMessage h;
  h.name = name;
  h.camera = TestCamera();
  return h;
}

Bytes HelloFrame(const HelloMessage& h) {
  return EncodeSessionFrame(SessionType::kHello, SerializeHello(h));
}

void Reseal(Bytes* frame) {
  const std::uint32_t crc = Crc32c(frame->data(), 16);
  for (int i = 0; i < 4; ++i) (*frame)[16 + i] = static_cast<std::uint8_t>(crc >> (8 * i));
}

// Sends `bytes` on a new connection and returns the reason of the server's Bye (nullopt:
// closed without one, or not closed within 10 s).
std::optional<ByeReason> Exchange(std::uint16_t port, const Bytes& bytes, bool half_close = false) {
  RawClient c;
  if (!c.Connect(port) || !c.SendBytes(bytes)) return std::nullopt;
  if (half_close) ::shutdown(c.fd(), SHUT_WR);
  std::vector<Frame> frames;
  if (!c.ReadUntilClosed(&frames, 10)) return std::nullopt;
  const std::optional<ByeMessage> bye = nettest::FindBye(frames);
  if (!bye) return std::nullopt;
  return bye->reason;
}

void Expect(Tally* t, const std::string& kind, std::optional<ByeReason> got, ByeReason want) {
  t->Note(kind, got == want,
          "expected bye '" + std::string(ByeReasonName(want)) + "', got " +
              (got ? "'" + std::string(ByeReasonName(*got)) + "'" : std::string("none")));
}

// Garbage, lengths, CRCs, versions and types, before any session.
void FramingAttacks(std::uint16_t port, Tally* t) {
  const std::string http = "GET / HTTP/1.1\r\nHost: x\r\n\r\n";
  Expect(t, "garbage", Exchange(port, Bytes(http.begin(), http.end())), ByeReason::kProtocolError);
  Bytes huge = HelloFrame(BaseHello("x"));
  for (int i = 0; i < 4; ++i) huge[8 + i] = 0xFF;  // a 4 GiB payload length
  Reseal(&huge);
  huge.resize(kFrameHeaderSize);
  Expect(t, "4 GiB length", Exchange(port, huge), ByeReason::kLimitExceeded);
  Bytes half = HelloFrame(BaseHello("x"));
  half.resize(half.size() / 2);
  t->Note("truncated frame", !Exchange(port, half, /*half_close=*/true).has_value(),
          "a bye to a peer that left mid-frame");
  Bytes crc = HelloFrame(BaseHello("x"));
  crc.back() ^= 1;
  Expect(t, "payload CRC", Exchange(port, crc), ByeReason::kProtocolError);
  Bytes version = HelloFrame(BaseHello("x"));
  version[4] = 1;
  Reseal(&version);
  Expect(t, "protocol version 1", Exchange(port, version), ByeReason::kUnsupportedVersion);
  for (std::uint8_t type : {0, 9, 200}) {
    Bytes typed = HelloFrame(BaseHello("x"));
    typed[5] = type;
    Reseal(&typed);
    Expect(t, "message type " + std::to_string(type), Exchange(port, typed),
           ByeReason::kProtocolError);
  }
}

// Eighteen kinds of absurd hello (a negative focal length is not one: ICL-NUIM has fy < 0).
void AbsurdHellos(std::uint16_t port, Tally* t) {
  std::vector<std::function<void(HelloMessage*)>> edits = {
      [](HelloMessage* h) { h->name = std::string(65, 'a'); },
      [](HelloMessage* h) { h->name = "../etc"; },
      [](HelloMessage* h) { h->name = ".hidden"; },
      [](HelloMessage* h) { h->name = "a b"; },
      [](HelloMessage* h) { h->camera.fx = 0; },
      [](HelloMessage* h) { h->camera.fy = std::numeric_limits<double>::infinity(); },
      [](HelloMessage* h) { h->camera.distortion[0] = std::nan(""); },
      [](HelloMessage* h) { h->camera.cx = std::nan(""); },
      [](HelloMessage* h) { h->camera.width = 0; },
      [](HelloMessage* h) { h->camera.height = 100000; },
      [](HelloMessage* h) { h->camera.depth_scale = 0; },
      [](HelloMessage* h) { h->camera.depth_scale = 1.0 / 0.0; },
      [](HelloMessage* h) { h->first_seq = 0; },
      [](HelloMessage* h) { h->first_seq = 9, h->next_seq = 3; },
      [](HelloMessage* h) { h->first_seq = 1, h->next_seq = (1ull << 62) + 5; },
  };
  for (std::size_t k = 0; k < edits.size(); ++k) {
    HelloMessage h = BaseHello("absurd");
    edits[k](&h);
    Expect(t, "absurd hello", Exchange(port, HelloFrame(h)), ByeReason::kProtocolError);
  }
  Bytes payload = SerializeHello(BaseHello("absurd"));
  Bytes flags = payload;
  flags[1] = 0x80;  // unknown flag bits
  Expect(t, "absurd hello", Exchange(port, EncodeSessionFrame(SessionType::kHello, flags)),
         ByeReason::kProtocolError);
  Bytes trailing = payload;
  trailing.push_back(0);
  Expect(t, "absurd hello", Exchange(port, EncodeSessionFrame(SessionType::kHello, trailing)),
         ByeReason::kProtocolError);
  payload[0] = 7;  // a hello of protocol version 7
  Expect(t, "absurd hello", Exchange(port, EncodeSessionFrame(SessionType::kHello, payload)),
         ByeReason::kUnsupportedVersion);
}

// Hello, then an Auth whose proof `prove` makes from the server's nonce and the hello sent
// (none: no proof); returns the reason of the server's (untagged) Bye.
using Prover = std::function<std::optional<Mac>(const Nonce& server_nonce, ByteSpan hello)>;
std::optional<ByeReason> AuthWith(std::uint16_t port, const Prover& prove) {
  RawClient c;
  HelloMessage h = BaseHello("intruder");
  for (int i = 0; i < 32; ++i) h.agent_nonce[i] = static_cast<std::uint8_t>(i * 5);
  const Bytes hello = SerializeHello(h);
  if (!c.Connect(port) || !c.SendBytes(EncodeSessionFrame(SessionType::kHello, hello))) {
    return std::nullopt;
  }
  std::optional<Frame> challenge = c.ReadFrame(5);
  if (!challenge) return std::nullopt;
  StatusOr<ChallengeMessage> ch = ParseChallenge(challenge->payload);
  if (!ch.ok()) return std::nullopt;
  AuthMessage auth;
  auth.proof = prove(ch->server_nonce, hello);
  if (!c.SendBytes(EncodeSessionFrame(SessionType::kAuth, SerializeAuth(auth))))
    return std::nullopt;
  std::vector<Frame> frames;
  c.ReadUntilClosed(&frames, 10);
  const std::optional<ByeMessage> bye = nettest::FindBye(frames);
  return bye ? std::optional(bye->reason) : std::nullopt;
}

// Messages before authentication, wrong and replayed keys.
void AuthenticationAttacks(std::uint16_t port, Tally* t) {
  Bytes data;
  AppendDataFrame(16, 1, Bytes(10, 1), &data);
  Expect(t, "data before hello", Exchange(port, data), ByeReason::kProtocolError);
  Expect(t, "auth before hello",
         Exchange(port, EncodeSessionFrame(SessionType::kAuth, Bytes(64, 1))),
         ByeReason::kProtocolError);
  Expect(t, "ack from a client", Exchange(port, EncodeSessionFrame(SessionType::kAck, Bytes(8, 0))),
         ByeReason::kProtocolError);
  Expect(t, "wrong key",
         AuthWith(port,
                  [&](const Nonce& server_nonce, ByteSpan hello) -> std::optional<Mac> {
                    return AgentProof(kOtherKey, server_nonce, hello);
                  }),
         ByeReason::kAuthFailed);
  Expect(t, "no key",
         AuthWith(port, [](const Nonce&, ByteSpan) -> std::optional<Mac> { return {}; }),
         ByeReason::kAuthFailed);
  // A proof made for one handshake, replayed in the next: the server's nonce differs.
  std::optional<Mac> recorded;
  AuthWith(port, [&](const Nonce& server_nonce, ByteSpan hello) -> std::optional<Mac> {
    recorded = AgentProof(kKey, server_nonce, hello);
    return Mac{};  // this first attempt fails anyway; what counts is the recorded proof
  });
  Expect(t, "replayed proof", AuthWith(port, [&](const Nonce&, ByteSpan) { return recorded; }),
         ByeReason::kAuthFailed);
}

// Another instance announcing the honest agent's name, with an absurd resume point.
void EvictionAttack(std::uint16_t port, Tally* t) {
  for (int variant = 0; variant < 2; ++variant) {
    RawClient c;
    c.identity = TestIdentity(60 + variant);
    HelloMessage h = BaseHello("honest");
    if (variant) h.camera.fx = 600;
    h.fresh = false;
    h.first_seq = h.next_seq = 1'000'000'000'000ull;
    const nettest::RawAnswer a = nettest::RawHandshakeWith(&c, port, h, kKey);
    const bool refused = a.bye && a.bye->reason == ByeReason::kRefused && !a.welcome &&
                         a.bye->text.find("525") == std::string::npos;
    t->Note("name takeover", refused, a.bye ? a.bye->text : "no refusal");
  }
}

// Dribbling: a hello one byte at a time, and a frame header in a session then one byte at
// a time; each must be cut at its deadline (handshake, frame).
void SlowAttacks(std::uint16_t port, Tally* t) {
  auto dribble = [](RawClient* c, const Bytes& bytes, double max_s) -> std::optional<ByeReason> {
    const double start = MonotonicSeconds();
    FrameDecoder decoder;
    std::vector<Frame> frames;
    std::vector<std::uint8_t> buffer(4096);
    for (std::size_t i = 0; MonotonicSeconds() - start < max_s; ++i) {
      const std::uint8_t byte = i < bytes.size() ? bytes[i] : 0x42;
      if (!WriteSome(c->fd(), &byte, 1).ok()) break;
      pollfd p{c->fd(), POLLIN, 0};
      ::poll(&p, 1, 100);  // the attacker's pace
      StatusOr<std::size_t> n = ReadSome(c->fd(), buffer.data(), buffer.size());
      if (!n.ok()) break;
      decoder.Feed(ByteSpan(buffer.data(), *n), &frames).IgnoreError();
      if (std::optional<ByeMessage> bye = nettest::FindBye(frames)) return bye->reason;
    }
    return std::nullopt;
  };
  RawClient hello;
  if (hello.Connect(port)) {
    Expect(t, "dribbled hello", dribble(&hello, HelloFrame(BaseHello("slow")), 20),
           ByeReason::kTimeout);
  }
  RawClient session;
  session.identity = TestIdentity(70);
  if (nettest::RawHandshake(&session, port, "slow-frame", kKey)) {
    WireFrame header = nettest::ForgeFrame(16, Bytes(8, 1), true);
    header.PutLe32(8, 60 << 10);  // within the frame limit
    header.PutLe32(16, Crc32c(header.bytes.data(), 16));
    Expect(
        t, "dribbled frame",
        dribble(&session, Bytes(header.bytes.begin(), header.bytes.begin() + kFrameHeaderSize), 30),
        ByeReason::kTimeout);
  } else {
    t->Note("dribbled frame", false, "handshake failed");
  }
}

// Idle connections held at once, then a storm of short ones (half with garbage).
void CrowdAttacks(std::uint16_t port, const Config& config, Tally* t) {
  std::vector<std::unique_ptr<RawClient>> idle;
  for (int i = 0; i < config.idle; ++i) {
    auto c = std::make_unique<RawClient>();
    if (c->Connect(port)) idle.push_back(std::move(c));
  }
  const std::string http = "GET / HTTP/1.1\r\n\r\n";
  int closed = 0;
  for (int i = 0; i < config.storm; ++i) {
    RawClient c;
    if (!c.Connect(port)) continue;
    if (i % 2) c.SendBytes(Bytes(http.begin(), http.end()));
    if (i % 2) {
      std::vector<Frame> frames;
      closed += c.ReadUntilClosed(&frames, 10);
    } else {
      ++closed;  // connects and leaves at once
    }
  }
  t->Note("connection storm", closed == config.storm,
          std::to_string(config.storm - closed) + " not closed by the server");
  int timed_out = 0;
  for (auto& c : idle) {
    std::vector<Frame> frames;
    c->ReadUntilClosed(&frames, 30);
    const std::optional<ByeMessage> bye = nettest::FindBye(frames);
    timed_out += bye && bye->reason == ByeReason::kTimeout;
  }
  t->Note("idle connections", timed_out == static_cast<int>(idle.size()),
          std::to_string(timed_out) + " of " + std::to_string(idle.size()) + " timed out");
}

// The man in the middle on the honest agent's path: the first time it sees each 40th data
// frame it swallows it and acknowledges it in the server's name; after each 55th it injects
// a keyframe of its own (once per sequence number: the agent resends after each).
struct MitmState {
  std::atomic<int> forged{0}, injected{0};
  std::atomic<std::uint64_t> forged_upto{0}, injected_upto{0};
};

nettest::TamperHook Mitm(MitmState* state) {
  return [=](bool from_agent, WireFrame f, std::vector<WireFrame>* forward,
             std::vector<WireFrame>* back) {
    std::uint64_t seq = 0;
    if (from_agent && f.type() == 16) {
      for (int i = 7; i >= 0; --i) seq = (seq << 8) | f.payload()[i];
    }
    if (seq > state->forged_upto.load() && seq % 40 == 0) {
      state->forged_upto.store(seq);
      ++state->forged;
      back->push_back(nettest::ForgeFrame(static_cast<std::uint8_t>(SessionType::kAck),
                                          SerializeAck({seq}), f.tagged()));
      return;
    }
    const bool tagged = f.tagged();
    forward->push_back(std::move(f));
    if (seq > state->injected_upto.load() && seq % 55 == 0) {
      state->injected_upto.store(seq);
      ++state->injected;
      WireFrame forged_kf;
      AppendDataFrame(16, seq + 1, nettest::SyntheticKeyframe(66, seq), &forged_kf.bytes,
                      tagged ? kFrameTagged : 0);
      if (tagged) forged_kf.bytes.insert(forged_kf.bytes.end(), kFrameTagSize, 0x5A);
      forward->push_back(std::move(forged_kf));
    }
  };
}

// Squatters fill every slot of a keyless server; an honest agent must still get in once
// their slots time out.
void KeylessSlots(const std::string& dir, Tally* t) {
  nettest::ServerProcess server;
  if (!server.Start({"--listen", "127.0.0.1:0", "--journal", dir + "/keyless", "--no-dense",
                     "--max-agents", "4", "--slot-timeout", "1"},
                    dir + "/keyless.log")) {
    t->Note("keyless slots", false, "server did not start");
    return;
  }
  std::vector<std::unique_ptr<RawClient>> squatters;
  for (int i = 0; i < 8; ++i) {
    auto c = std::make_unique<RawClient>();
    c->identity = TestIdentity(200 + i);
    const nettest::RawAnswer a =
        nettest::RawHandshakeWith(c.get(), server.port(), BaseHello("squat" + std::to_string(i)));
    if (a.welcome) {
      c->SendData(16, a.welcome->last_stored_seq + 1, nettest::SyntheticKeyframe(200 + i, 0));
      squatters.push_back(std::move(c));
    } else if (i < 4 || !a.bye || a.bye->reason != ByeReason::kServerFull) {
      t->Note("keyless slots", false, "squatter " + std::to_string(i) + " not as expected");
    }
  }
  t->Note("keyless slots: full", squatters.size() == 4, "4 slots, then 'server full'");
  for (auto& c : squatters) c->ReadFrame(5);  // their acks
  squatters.clear();
  AgentLinkOptions o;
  o.server = "127.0.0.1:" + std::to_string(server.port());
  o.name = "late";
  o.camera = TestCamera();
  o.backoff_initial_s = 0.05;
  o.backoff_max_s = 0.2;
  auto late = AgentLink::Create(o);
  bool delivered = false;
  if (late.ok()) {
    for (int i = 0; i < 5; ++i) {
      (*late)
          ->Send(MessageType::kKeyframe, nettest::SyntheticKeyframe(300, i))
          .status()
          .IgnoreError();
    }
    delivered = (*late)->Flush(30).ok();
  }
  t->Note("keyless slots: honest agent served", delivered, "not served after the slot time-out");
  server.Signal(SIGTERM);
  server.Wait();
}

// The honest agent: sends keyframes at 20 Hz until told to stop, through the man in the
// middle; counts acknowledgements so the run can wait for them.
class HonestAgent {
 public:
  bool Start(const std::string& dir, std::uint16_t port) {
    AgentLinkOptions o;
    o.server = "127.0.0.1:" + std::to_string(port);
    o.name = "honest";
    o.camera = TestCamera();
    o.psk = kKey;
    o.spill_dir = dir + "/honest.spill";
    o.backoff_initial_s = 0.01;
    o.backoff_max_s = 0.2;
    o.on_acked = [this](std::uint64_t, std::uint64_t last) {
      std::lock_guard<std::mutex> lock(mutex_);
      acked_ = last;
      cv_.notify_all();
    };
    StatusOr<std::unique_ptr<AgentLink>> link = AgentLink::Create(o);
    if (!link.ok()) return false;
    link_ = std::move(*link);
    thread_ = std::thread([this] {
      for (std::uint64_t i = 0; !stop_.load(); ++i) {
        if (!link_->Send(MessageType::kKeyframe, Honest(i)).ok()) return;
        std::this_thread::sleep_for(std::chrono::milliseconds(50));  // the agent's pace
      }
    });
    return true;
  }
  bool WaitAcked(std::uint64_t n, double timeout_s) {
    std::unique_lock<std::mutex> lock(mutex_);
    return cv_.wait_for(lock, std::chrono::duration<double>(timeout_s),
                        [&] { return acked_ >= n; });
  }
  // Stops sending and waits for every acknowledgement.
  Status Finish() {
    stop_.store(true);
    if (thread_.joinable()) thread_.join();
    return link_->Flush(60);
  }
  AgentLinkStats stats() const { return link_->stats(); }
  ~HonestAgent() {
    stop_.store(true);
    if (thread_.joinable()) thread_.join();
  }

 private:
  std::unique_ptr<AgentLink> link_;
  std::thread thread_;
  std::atomic<bool> stop_{false};
  std::mutex mutex_;
  std::condition_variable cv_;
  std::uint64_t acked_ = 0;
};

// The journals hold the honest agent's messages 1..n exactly, and nothing else.
void CheckJournals(const std::string& dir, std::uint64_t queued, Tally* t) {
  int with_data = 0;
  for (int id = 1; id < 64; ++id) {
    const std::string path = dir + "/" + JournalFileName(AgentId(static_cast<std::uint16_t>(id)));
    if (!FileExists(path)) continue;
    std::string name;
    std::uint64_t expected = 1;
    bool same = true;
    JournalVisitor v;
    v.on_info = [&](const JournalAgentInfo& info) {
      name = info.name;
      return Status::Ok();
    };
    v.on_record = [&](const JournalRecord& r) {
      same = same && r.seq == expected &&
             Bytes(r.message.begin(), r.message.end()) == Honest(expected - 1);
      ++expected;
      return Status::Ok();
    };
    StatusOr<JournalScan> scan = ScanJournalFile(path, v);
    if (!scan.ok()) {
      t->Note("journal", false, scan.status().ToString());
      continue;
    }
    with_data += scan->records > 0;
    if (name == "honest") {
      t->Note("honest journal: every message once, in order, byte for byte",
              same && scan->records == queued,
              std::to_string(scan->records) + " records for " + std::to_string(queued) + " queued");
    } else if (scan->records > 0) {
      t->Note("no attacker data journaled", false, name + " has " + std::to_string(scan->records));
    }
  }
  t->Note("no attacker data journaled", with_data == 1, std::to_string(with_data) + " journals");
}

// The transport's lines in the log (the back-end's own warnings about the synthetic
// keyframes' content are not what this run is about), and how often each kind (the text
// after the source position, up to the first digit or quote) appears.
int CountTransportLines(const std::string& path, std::map<std::string, int>* kinds) {
  std::ifstream in(path);
  int n = 0;
  for (std::string line; std::getline(in, line);) {
    bool transport = false;
    for (const char* file : {" server.cc:", " server_session.cc:", " refusal_log.cc:",
                             " journal_stage.cc:", " journal.cc:"}) {
      transport = transport || line.find(file) != std::string::npos;
    }
    if (!transport) continue;
    ++n;
    const std::size_t from = std::min(line.size(), line.find("] ") + 2);
    std::string kind = line.substr(from, 48);
    kind = kind.substr(0, kind.find_first_of("0123456789'"));
    ++(*kinds)[kind];
  }
  return n;
}

}  // namespace
}  // namespace ccmd

int main(int argc, char** argv) {
  using namespace ccmd;
  CLI::App app{
      "A bounded attack run against a ccmd_server it starts on loopback (see the file's "
      "header). Exit status 0 when every check holds."};
  Config config;
  app.add_option("--rounds", config.rounds,
                 "Rounds of attacks, each ending with kill -9 and --resume")
      ->check(CLI::Range(1, 100))
      ->capture_default_str();
  app.add_option("--storm", config.storm, "Connections per storm")
      ->check(CLI::Range(1, 100000))
      ->capture_default_str();
  app.add_option("--idle", config.idle, "Idle connections held at once (at most 30)")
      ->check(CLI::Range(0, 30))
      ->capture_default_str();
  CLI11_PARSE(app, argc, argv);
  SetMinLogLevel(LogLevel::ERROR);
  const double start = MonotonicSeconds();
  testing::TempDir dir;
  Tally tally;
  const std::string key_file = dir.File("ccmd.key");
  if (!WriteFileAtomic(key_file, kKey).ok()) return 1;
  ::chmod(key_file.c_str(), 0600);
  const std::string log = dir.File("server.log");
  std::vector<std::string> args = {"--listen",   "127.0.0.1:0",
                                   "--journal",  dir.File("journal"),
                                   "--psk-file", key_file,
                                   "--no-dense", "--handshake-timeout",
                                   "1",          "--idle-timeout",
                                   "3",          "--frame-timeout",
                                   "2",          "--max-frame-bytes",
                                   "262144"};
  auto server = std::make_unique<nettest::ServerProcess>();
  if (!server->Start(args, log)) {
    std::fprintf(stderr, "ccmd_attack: cannot start ccmd_server\n");
    return 1;
  }
  MitmState mitm;
  nettest::TamperProxy proxy(Mitm(&mitm));
  HonestAgent honest;
  if (!proxy.Start(server->port()) || !honest.Start(dir.path(), proxy.port())) return 1;
  tally.Note("honest agent: first 20 (large) messages acknowledged", honest.WaitAcked(20, 60));
  for (int round = 0; round < config.rounds; ++round) {
    const std::uint16_t port = server->port();
    FramingAttacks(port, &tally);
    AbsurdHellos(port, &tally);
    AuthenticationAttacks(port, &tally);
    EvictionAttack(port, &tally);
    SlowAttacks(port, &tally);
    CrowdAttacks(port, config, &tally);
    // kill -9 while the honest agent sends, then resume with a smaller frame limit than
    // the journal's first records.
    server->Signal(SIGKILL);
    server->Wait();
    args = {"--listen",   "127.0.0.1:0",
            "--resume",   dir.File("journal"),
            "--psk-file", key_file,
            "--no-dense", "--handshake-timeout",
            "1",          "--idle-timeout",
            "3",          "--frame-timeout",
            "2",          "--max-frame-bytes",
            "65536"};
    server = std::make_unique<nettest::ServerProcess>();
    const bool resumed = server->Start(args, log);
    tally.Note("kill -9, then --resume with a smaller frame limit", resumed);
    if (!resumed) break;
    proxy.SetTarget(server->port());
  }
  KeylessSlots(dir.path(), &tally);
  const Status flushed = honest.Finish();
  const AgentLinkStats stats = honest.stats();
  tally.Note("honest agent: every message acknowledged", flushed.ok() && stats.unacked == 0,
             flushed.ToString());
  tally.Note("man in the middle: forged acks and injected keyframes tried",
             mitm.forged.load() > 0 && mitm.injected.load() > 0);
  tally.Note("honest agent: forged frames detected", stats.auth_failures >= 1,
             std::to_string(stats.auth_failures));
  proxy.Stop();
  server->Signal(SIGTERM);
  tally.Note("server stops cleanly", server->Wait() == 0);
  CheckJournals(dir.File("journal"), stats.queued, &tally);
  std::map<std::string, int> kinds;
  const int lines = CountTransportLines(log, &kinds);
  // Hundreds of refused connections per round; the log has a few lines per interval and per
  // honest reconnection (each man-in-the-middle attempt costs one).
  const int bound = 60 + 20 * config.rounds + 6 * static_cast<int>(stats.sessions);
  tally.Note("server log stays small (transport lines)", lines <= bound,
             std::to_string(lines) + " lines, bound " + std::to_string(bound));

  int runs = 0, ok = 0;
  std::printf("| attack or check | runs | as expected |\n|---|---|---|\n");
  for (const auto& [kind, r] : tally.runs) {
    std::printf("| %s | %d | %d |\n", kind.c_str(), r.first, r.second);
    runs += r.first;
    ok += r.second;
  }
  std::printf(
      "\nhonest agent: %llu queued, %llu acknowledged, %llu sessions, %llu resent, %llu "
      "forged frames detected; man in the middle: %d acks forged, %d keyframes injected\n",
      static_cast<unsigned long long>(stats.queued), static_cast<unsigned long long>(stats.acked),
      static_cast<unsigned long long>(stats.sessions),
      static_cast<unsigned long long>(stats.resent),
      static_cast<unsigned long long>(stats.auth_failures), mitm.forged.load(),
      mitm.injected.load());
  std::printf("server log: %d transport lines; %d of %d checks as expected in %.1f s\n", lines, ok,
              runs, MonotonicSeconds() - start);
  for (const std::string& f : tally.failures) std::printf("FAILED %s\n", f.c_str());
  if (lines > bound) {
    std::printf("the server log's lines by kind:\n");
    for (const auto& [kind, n] : kinds) {
      if (n > 2) std::printf("%6d  %s\n", n, kind.c_str());
    }
  }
  return tally.failures.empty() ? 0 : 1;
}
