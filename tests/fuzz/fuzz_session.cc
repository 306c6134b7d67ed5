// Fuzz target: the transport's session messages (hello, challenge, auth, welcome, ack, bye,
// heartbeat), the data envelope, the journal's info and update records and the journal
// scanner, all on the same input.

#include <cstring>

#include "libccmd/net/journal.h"
#include "libccmd/net/session_messages.h"
#include "tests/fuzz/fuzz_target.h"

namespace ccmd::fuzz {

namespace {

SessionCamera Camera() {
  SessionCamera c;
  c.fx = c.fy = 525;
  c.cx = 319.5;
  c.cy = 239.5;
  c.width = 640;
  c.height = 480;
  c.depth_scale = 5000;
  return c;
}

}  // namespace

std::vector<std::vector<std::uint8_t>> FuzzSeeds() {
  HelloMessage hello;
  hello.name = "robot-1";
  hello.camera = Camera();
  hello.fresh = false;
  hello.first_seq = 4;
  hello.next_seq = 9;
  WelcomeMessage welcome;
  welcome.agent = AgentId(3);
  welcome.last_stored_seq = 8;
  welcome.max_payload_bytes = 1 << 24;
  welcome.idle_timeout_ms = 30000;
  ChallengeMessage challenge;
  challenge.key_required = true;
  JournalAgentInfo info{AgentId(3), "robot-1", Camera()};
  info.max_payload_bytes = 4096;
  info.verifier.fill(0x42);
  std::vector<std::uint8_t> journal =
      EncodeFrame(kJournalInfoRecord, 0, SerializeJournalInfo(info));
  AppendDataFrame(16, 1, std::vector<std::uint8_t>(30, 1), &journal);
  const std::vector<std::uint8_t> update =
      EncodeFrame(kJournalUpdateRecord, 0, SerializeJournalUpdate({1 << 16, {}}));
  journal.insert(journal.end(), update.begin(), update.end());
  AppendDataFrame(17, 2, std::vector<std::uint8_t>(5, 2), &journal);
  return {SerializeHello(hello),
          SerializeChallenge(challenge),
          std::vector<std::uint8_t>(32, 0x11),
          std::vector<std::uint8_t>(64, 0x12),
          SerializeWelcome(welcome),
          SerializeAck({77}),
          SerializeBye({ByeReason::kFrameAuthFailed, "forged"}),
          SerializeJournalInfo(info),
          SerializeJournalUpdate({4096, info.verifier}),
          journal};
}

}  // namespace ccmd::fuzz

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  using namespace ccmd;
  const ByteSpan in(data, size);
  auto same = [&](const std::vector<std::uint8_t>& again) {
    return again.size() == size && (size == 0 || std::memcmp(again.data(), data, size) == 0);
  };
  // Every field is fixed-width and checked, so whatever parses serializes back identically.
  if (StatusOr<HelloMessage> m = ParseHello(in); m.ok()) {
    if (!ValidateAgentName(m->name).ok()) fuzz::FuzzFail("hello accepted a bad name");
    if (!same(SerializeHello(*m))) fuzz::FuzzFail("hello round trip");
  }
  if (StatusOr<ChallengeMessage> m = ParseChallenge(in); m.ok()) {
    if (!same(SerializeChallenge(*m))) fuzz::FuzzFail("challenge round trip");
  }
  if (StatusOr<AuthMessage> m = ParseAuth(in); m.ok()) {
    if (!same(SerializeAuth(*m))) fuzz::FuzzFail("auth round trip");
  }
  if (StatusOr<WelcomeMessage> m = ParseWelcome(in); m.ok()) {
    if (!same(SerializeWelcome(*m))) fuzz::FuzzFail("welcome round trip");
  }
  if (StatusOr<AckMessage> m = ParseAck(in); m.ok()) {
    if (!same(SerializeAck(*m))) fuzz::FuzzFail("ack round trip");
  }
  if (StatusOr<ByeMessage> m = ParseBye(in); m.ok()) {
    if (m->text.size() > kMaxByeTextBytes) fuzz::FuzzFail("bye text over the limit");
    for (char c : m->text) {
      if (c < 0x20 || c >= 0x7F) fuzz::FuzzFail("bye text not printable");
    }
  }
  (void)ParseHeartbeat(in);
  if (StatusOr<DataEnvelope> e = ParseDataEnvelope(in); e.ok()) {
    if (e->seq == 0 || e->seq > kMaxSequenceNumber ||
        e->message.size() + kDataEnvelopeBytes != size) {
      fuzz::FuzzFail("data envelope");
    }
  }
  if (StatusOr<JournalAgentInfo> info = ParseJournalInfo(in); info.ok()) {
    // Version 2 records round-trip; version 1 ones (no limit) gain the new fields.
    const std::vector<std::uint8_t> again = SerializeJournalInfo(*info);
    if (info->max_payload_bytes != 0 && !same(again)) fuzz::FuzzFail("journal info round trip");
    if (info->max_payload_bytes == 0 && again.size() != size + 4 + kIdentitySize) {
      fuzz::FuzzFail("version 1 journal info");
    }
  }
  if (StatusOr<JournalUpdate> u = ParseJournalUpdate(in); u.ok()) {
    if (!same(SerializeJournalUpdate(*u))) fuzz::FuzzFail("journal update round trip");
  }
  std::uint64_t last = 0;
  JournalVisitor visitor;
  visitor.on_record = [&](const JournalRecord& r) {
    if (r.seq <= last) fuzz::FuzzFail("journal sequence not increasing");
    last = r.seq;
    return Status::Ok();
  };
  StatusOr<JournalScan> scan = ScanJournalBytes(in, visitor, {.max_payload_bytes = 1u << 16});
  if (scan.ok() && scan->valid_bytes + scan->torn_bytes != size) {
    fuzz::FuzzFail("journal scan does not account for every byte");
  }
  return 0;
}
