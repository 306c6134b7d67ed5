#include "libccmd/net/journal_stage.h"

#include <dirent.h>
#include <unistd.h>

#include <algorithm>

#include "libccmd/net/psk.h"
#include "libccmd/util/file_util.h"
#include "libccmd/util/logging.h"
#include "libccmd/util/timer.h"

namespace ccmd {

// ---------------------------------------------------------------- DeliveryStage

DeliveryStage::DeliveryStage(MessageConsumer* consumer, std::size_t capacity, TrafficStats* stats)
    : consumer_(consumer), stats_(stats), queue_(capacity) {}

void DeliveryStage::Start() {
  thread_ = std::thread([this] { Run(); });
}

void DeliveryStage::Push(DeliveryItem item) { queue_.Push(std::move(item)); }

void DeliveryStage::WaitReplayFinished() {
  std::unique_lock<std::mutex> lock(mutex_);
  replay_done_cv_.wait(lock, [&] { return replay_done_; });
}

void DeliveryStage::Stop() {
  queue_.Close();
  if (thread_.joinable()) thread_.join();
}

void DeliveryStage::Run() {
  while (std::optional<DeliveryItem> item = queue_.Pop()) {
    switch (item->kind) {
      case DeliveryItem::Kind::kAgentKnown:
        consumer_->OnAgentKnown(item->agent, item->from_journal);
        break;
      case DeliveryItem::Kind::kConnected:
        consumer_->OnAgentConnected(item->id, item->value);
        break;
      case DeliveryItem::Kind::kDisconnected:
        consumer_->OnAgentDisconnected(item->id, item->reason);
        break;
      case DeliveryItem::Kind::kMessage: {
        const AgentId agent = item->message.agent;
        const std::uint64_t seq = item->message.seq;
        const bool replayed = item->message.replayed;
        consumer_->OnMessage(std::move(item->message));
        stats_->AddDelivered(agent, seq, replayed);
        break;
      }
      case DeliveryItem::Kind::kReplayFinished: {
        consumer_->OnReplayFinished(item->value);
        std::lock_guard<std::mutex> lock(mutex_);
        replay_done_ = true;
        replay_done_cv_.notify_all();
        break;
      }
    }
  }
}

// ---------------------------------------------------------------- JournalStage

JournalStage::JournalStage(JournalStageOptions options, DeliveryStage* delivery, WakeFd* wake,
                           TrafficStats* stats)
    : options_(std::move(options)),
      delivery_(delivery),
      wake_(wake),
      stats_(stats),
      queue_(options_.queue_capacity) {}

namespace {

// Records that from here on the journal may hold payloads up to `limit`, if that is more
// than it recorded (a resume with a larger --max-frame-bytes): a later replay must accept
// the larger records. A smaller limit needs nothing: every record fits the recorded one.
Status RaiseRecordedLimit(JournalAgentInfo* info, JournalWriter* writer, std::uint32_t limit) {
  if (info->max_payload_bytes >= limit) return Status::Ok();
  CCMD_RETURN_IF_ERROR(writer->AppendUpdate({limit, {}}));
  info->max_payload_bytes = limit;
  return Status::Ok();
}

// Journal files in `dir`, sorted by agent id.
StatusOr<std::vector<std::pair<AgentId, std::string>>> ListJournals(const std::string& dir) {
  std::vector<std::pair<AgentId, std::string>> files;
  DIR* d = ::opendir(dir.c_str());
  if (d == nullptr) return IoError("cannot open journal folder " + dir);
  while (dirent* e = ::readdir(d)) {
    AgentId id;
    if (ParseJournalFileName(e->d_name, &id)) files.emplace_back(id, JoinPath(dir, e->d_name));
  }
  ::closedir(d);
  std::sort(files.begin(), files.end());
  return files;
}

}  // namespace

Status JournalStage::CheckNoJournals() {
  CCMD_RETURN_IF_ERROR(MakeDirectories(options_.dir));
  CCMD_ASSIGN_OR_RETURN(auto files, ListJournals(options_.dir));
  if (!files.empty()) {
    return InvalidArgument("journal folder " + options_.dir + " already holds " +
                           std::to_string(files.size()) +
                           " agent journal(s) from an earlier run; resume them with --resume " +
                           options_.dir + ", or choose an empty folder");
  }
  return Status::Ok();
}

Status JournalStage::Announce(Agent* agent, bool from_journal, std::vector<DeliveryItem>* out) {
  if (agent->announced) return Status::Ok();
  agent->announced = true;
  DeliveryItem d;
  d.kind = DeliveryItem::Kind::kAgentKnown;
  d.agent = AgentDescription{agent->info.id, agent->info.name, agent->info.camera};
  d.from_journal = from_journal;
  out->push_back(std::move(d));
  return Status::Ok();
}

StatusOr<std::uint64_t> JournalStage::Resume() {
  CCMD_RETURN_IF_ERROR(MakeDirectories(options_.dir));
  CCMD_ASSIGN_OR_RETURN(auto files, ListJournals(options_.dir));
  std::uint64_t total = 0;
  for (const auto& file : files) {
    // Named copies: lambdas below capture them (clang does not capture structured bindings).
    const AgentId file_id = file.first;
    const std::string& path = file.second;
    Agent agent;
    JournalVisitor visitor;
    visitor.on_info = [&](const JournalAgentInfo& info) -> Status {
      if (info.id != file_id) {
        return Corrupt(path + " holds the journal of agent id " + std::to_string(info.id.value()));
      }
      if (by_name_.count(info.name)) {
        return Corrupt(path + ": agent name '" + info.name + "' is also in " +
                       JournalFileName(by_name_[info.name]));
      }
      agent.info = info;
      std::vector<DeliveryItem> announce;
      CCMD_RETURN_IF_ERROR(Announce(&agent, /*from_journal=*/true, &announce));
      for (DeliveryItem& d : announce) delivery_->Push(std::move(d));
      return Status::Ok();
    };
    visitor.on_record = [&](const JournalRecord& record) -> Status {
      DeliveryItem d;
      d.kind = DeliveryItem::Kind::kMessage;
      d.message.agent = file_id;
      d.message.seq = record.seq;
      d.message.type = record.type;
      d.message.payload.assign(record.message.begin(), record.message.end());
      d.message.replayed = true;
      delivery_->Push(std::move(d));
      return Status::Ok();
    };
    // Each journal is read with the limits it records, whatever this run's limit is.
    CCMD_ASSIGN_OR_RETURN(const JournalScan scan, ScanJournalFile(path, visitor));
    if (!scan.has_info) {
      // The server stopped while creating this journal: nothing in it was acknowledged.
      CCMD_LOG(WARNING) << path << ": no complete info record (" << scan.torn_bytes
                        << " bytes; the server stopped while registering this agent); removed";
      if (::unlink(path.c_str()) != 0) return IoError("cannot remove " + path);
      continue;
    }
    if (scan.torn_bytes > 0) {
      CCMD_LOG(WARNING) << path << ": cut off a torn tail of " << scan.torn_bytes
                        << " bytes at offset " << scan.valid_bytes << " (" << scan.torn_reason
                        << "; left by a crash, never acknowledged)";
      stats_->Count("journal_torn_tails");
    }
    if (scan.gaps > 0) {
      CCMD_LOG(WARNING) << path << ": " << scan.gaps << " gap(s) in the sequence numbers";
    }
    CCMD_ASSIGN_OR_RETURN(agent.writer, JournalWriter::OpenForAppend(path, scan.valid_bytes));
    agent.info = scan.info;  // with its update records applied
    CCMD_RETURN_IF_ERROR(
        RaiseRecordedLimit(&agent.info, agent.writer.get(), options_.max_payload_bytes));
    agent.written_seq = agent.durable_seq = scan.last_seq;
    // Restored agents get a slot time-out's grace to come back before new names take it.
    agent.last_detach = MonotonicSeconds();
    next_id_ = std::max<std::uint32_t>(next_id_, file_id.value() + 1u);
    CCMD_LOG(INFO) << "resumed agent " << agent.info.id << " '" << agent.info.name
                   << "': " << scan.records << " messages, last sequence number " << scan.last_seq;
    total += scan.records;
    by_name_[agent.info.name] = file_id;
    agents_[file_id] = std::move(agent);
  }
  stats_->Count("replayed_messages", total);
  return total;
}

bool JournalStage::TryPush(StageItem& item) {
  // With one producer, room seen here cannot disappear before the push.
  if (queue_.size() >= queue_.capacity()) return false;
  return queue_.TryPush(std::move(item));
}

void JournalStage::Start() {
  thread_ = std::thread([this] { Run(); });
}

void JournalStage::Stop() {
  queue_.Close();
  if (thread_.joinable()) thread_.join();
}

void JournalStage::TakeFeedback(StageFeedback* out) {
  std::lock_guard<std::mutex> lock(feedback_mutex_);
  *out = std::move(feedback_);
  feedback_ = StageFeedback{};
}

void JournalStage::Run() {
  std::vector<StageItem> items;
  while (std::optional<StageItem> first = queue_.Pop()) {
    items.clear();
    items.push_back(std::move(*first));
    while (items.size() < options_.max_batch) {
      std::optional<StageItem> more = queue_.TryPop();
      if (!more) break;
      items.push_back(std::move(*more));
    }
    // The queue has room again: let the I/O thread resume reading if it had stopped.
    wake_->Signal();
    ProcessBatch(&items);
  }
}

void JournalStage::ProcessBatch(std::vector<StageItem>* items) {
  Batch batch;
  for (StageItem& item : *items) {
    switch (item.kind) {
      case StageItem::Kind::kAttach:
        Attach(item, &batch);
        break;
      case StageItem::Kind::kData:
        Data(&item, &batch);
        break;
      case StageItem::Kind::kDetach:
        Detach(item, &batch);
        break;
    }
  }
  // Group commit: one fdatasync per journal written in this batch, before any ack.
  StageFeedback feedback;
  for (const auto& [id, unused] : batch.touched) {
    Agent& a = agents_[id];
    if (options_.fsync) {
      Status s = a.writer->Sync();
      if (!s.ok()) {
        Fail(id, s, &batch, &feedback);
        continue;
      }
    }
    a.durable_seq = a.written_seq;
    feedback.stored[id] = a.durable_seq;
  }
  feedback.attached = std::move(batch.attached);
  feedback.freed_bytes = std::move(batch.freed);
  feedback.forgotten = std::move(batch.forgotten);
  {
    std::lock_guard<std::mutex> lock(feedback_mutex_);
    for (AttachResult& r : feedback.attached) feedback_.attached.push_back(std::move(r));
    for (const auto& [id, seq] : feedback.stored) feedback_.stored[id] = seq;
    for (const auto& [id, n] : feedback.freed_bytes) feedback_.freed_bytes[id] += n;
    for (auto& f : feedback.failed) feedback_.failed.push_back(std::move(f));
    for (AgentId id : feedback.forgotten) feedback_.forgotten.push_back(id);
  }
  wake_->Signal();
  // Only now, with the records durable, does the consumer see them.
  for (DeliveryItem& d : batch.deliveries) delivery_->Push(std::move(d));
}

void JournalStage::Fail(AgentId id, const Status& status, Batch* batch, StageFeedback* feedback) {
  Agent& a = agents_[id];
  CCMD_LOG(ERROR) << "journal of agent " << id << " '" << a.info.name
                  << "' failed: " << status.ToString() << "; unsynced records discarded";
  stats_->Count("journal_failures");
  Status cut = a.writer->RollBack();
  if (!cut.ok()) CCMD_LOG(ERROR) << cut.ToString();
  a.written_seq = a.durable_seq;
  // Nothing after the durable point may reach the consumer or be acknowledged.
  auto& d = batch->deliveries;
  d.erase(std::remove_if(d.begin(), d.end(),
                         [&](const DeliveryItem& x) {
                           return x.kind == DeliveryItem::Kind::kMessage && x.message.agent == id &&
                                  x.message.seq > a.durable_seq;
                         }),
          d.end());
  for (AttachResult& r : batch->attached) {
    if (r.status.ok() && r.agent == id) {
      r.status = status;
      r.reason = ByeReason::kServerError;
    }
  }
  feedback->failed.emplace_back(id, status);
}

int JournalStage::ActiveAgents(double now) const {
  int active = 0;
  for (const auto& [id, a] : agents_) {
    active += a.connections > 0 || now - a.last_detach < options_.slot_timeout_s;
  }
  return active;
}

JournalStage::Agent* JournalStage::CheckRegistered(const StageItem& item, AttachResult* refusal) {
  const HelloMessage& hello = item.hello;
  Agent* agent = &agents_[by_name_.at(hello.name)];
  if (!IsZero(agent->info.verifier) && !ConstantTimeEquals(agent->info.verifier, item.verifier)) {
    // Nothing about the registered agent (camera, sequence numbers) goes to this peer.
    stats_->Count("refused_identity");
    refusal->reason = ByeReason::kRefused;
    refusal->status = PermissionDenied(
        "the name '" + hello.name +
        "' belongs to an agent registered earlier, and this agent cannot prove it is that one "
        "(its identity file, kept in its spill folder, is missing or differs); use another "
        "name");
    return nullptr;
  }
  if (IsZero(agent->info.verifier)) {
    // A journal of protocol version 1 recorded no identity: the first to connect claims it.
    const Status s = agent->writer->AppendUpdate({agent->info.max_payload_bytes, item.verifier});
    if (!s.ok()) {
      refusal->reason = ByeReason::kServerError;
      refusal->status = s;
      return nullptr;
    }
    agent->info.verifier = item.verifier;
    CCMD_LOG(WARNING) << "agent '" << hello.name
                      << "': its journal (protocol version 1) recorded no identity; adopted "
                         "the one this connection presented";
  }
  if (!(agent->info.camera == hello.camera)) {
    refusal->reason = ByeReason::kRefused;
    refusal->status = InvalidArgument("agent '" + hello.name + "' is registered with camera " +
                                      DescribeCamera(agent->info.camera) + " but announces " +
                                      DescribeCamera(hello.camera) +
                                      "; a different camera needs a new agent name");
    return nullptr;
  }
  return agent;
}

JournalStage::Agent* JournalStage::RegisterProvisionally(const StageItem& item,
                                                         AttachResult* refusal) {
  const int active = ActiveAgents(item.received_time);
  if (active >= options_.max_agents || next_id_ > 0xFFFF) {
    refusal->reason = ByeReason::kServerFull;
    refusal->status = OutOfRange(
        next_id_ > 0xFFFF
            ? std::string("the server has given out every agent id in this run")
            : "server full: all " + std::to_string(options_.max_agents) +
                  " agent slots are in use (--max-agents); a slot frees when its agent has "
                  "been disconnected for " +
                  std::to_string(static_cast<int>(options_.slot_timeout_s)) +
                  " s (--slot-timeout). This agent keeps trying");
    return nullptr;
  }
  const AgentId id(static_cast<std::uint16_t>(next_id_++));
  Agent a;
  a.info = JournalAgentInfo{id, item.hello.name, item.hello.camera, options_.max_payload_bytes,
                            item.verifier};
  by_name_[item.hello.name] = id;
  return &(agents_[id] = std::move(a));
}

Status JournalStage::CheckResumePoint(const HelloMessage& hello, bool journaled, Agent* agent) {
  if (hello.fresh) return Status::Ok();
  const std::uint64_t last = agent->written_seq;
  if (hello.next_seq - 1 < last) {
    return InvalidArgument("the server holds " + std::to_string(last) + " messages of agent '" +
                           hello.name + "' but the agent has sent only " +
                           std::to_string(hello.next_seq - 1));
  }
  if (hello.first_seq <= last + 1) return Status::Ok();
  if (journaled) {
    // Everything acknowledged was journaled first: a journal that ends earlier is not the
    // one that acknowledged these messages, and jumping ahead would lose them silently.
    stats_->Count("refused_resume_point");
    return InvalidArgument(
        "agent '" + hello.name + "' says messages up to " + std::to_string(hello.first_seq - 1) +
        " were acknowledged, but this server's journal of it ends at message " +
        std::to_string(last) +
        ": it is not the journal that acknowledged them (an older copy?). Resume the server "
        "from the journal folder it ran with, or give the agent a new name");
  }
  // A name new to this server: its messages up to first_seq - 1 were acknowledged by a
  // server whose journal is not here (started without its --resume folder).
  CCMD_LOG(WARNING) << "agent '" << hello.name << "': messages 1.." << hello.first_seq - 1
                    << " were acknowledged earlier but are not in this server's journal "
                       "(started without its --resume folder?); continuing after the gap";
  stats_->Count("sequence_gaps");
  agent->written_seq = agent->durable_seq = hello.first_seq - 1;
  return Status::Ok();
}

void JournalStage::Attach(const StageItem& item, Batch* batch) {
  AttachResult result;
  result.conn = item.conn;
  const bool registered = by_name_.count(item.hello.name) > 0;
  Agent* agent = registered ? CheckRegistered(item, &result) : RegisterProvisionally(item, &result);
  if (agent == nullptr) {
    batch->attached.push_back(std::move(result));
    return;
  }
  const Status resume = CheckResumePoint(item.hello, agent->writer != nullptr, agent);
  if (!resume.ok()) {
    result.reason = ByeReason::kRefused;
    result.status = resume;
    batch->attached.push_back(std::move(result));
    return;
  }
  ++agent->connections;
  if (agent->writer) {
    Announce(agent, /*from_journal=*/false, &batch->deliveries).IgnoreError();
    DeliveryItem connected;
    connected.kind = DeliveryItem::Kind::kConnected;
    connected.id = agent->info.id;
    connected.value = agent->written_seq;
    batch->deliveries.push_back(std::move(connected));
  }
  result.agent = agent->info.id;
  result.last_stored = agent->written_seq;
  batch->attached.push_back(std::move(result));
}

void JournalStage::Detach(const StageItem& item, Batch* batch) {
  auto it = agents_.find(item.agent);
  if (it == agents_.end()) return;
  Agent& a = it->second;
  a.connections = std::max(0, a.connections - 1);
  if (a.connections == 0) a.last_detach = item.received_time;
  if (a.announced) {
    DeliveryItem d;
    d.kind = DeliveryItem::Kind::kDisconnected;
    d.id = item.agent;
    d.reason = item.reason;
    batch->deliveries.push_back(std::move(d));
  }
  if (a.connections == 0 && !a.writer) {
    // Registered in this run and gone without sending anything: nothing to keep.
    by_name_.erase(a.info.name);
    agents_.erase(it);
    batch->forgotten.push_back(item.agent);
  }
}

Status JournalStage::Persist(Agent* agent, Batch* batch) {
  const AgentId id = agent->info.id;
  CCMD_ASSIGN_OR_RETURN(
      agent->writer,
      JournalWriter::Create(JoinPath(options_.dir, JournalFileName(id)), agent->info));
  CCMD_LOG(INFO) << "registered agent " << id << " '" << agent->info.name << "' ("
                 << DescribeCamera(agent->info.camera) << ")";
  Announce(agent, /*from_journal=*/false, &batch->deliveries).IgnoreError();
  DeliveryItem connected;
  connected.kind = DeliveryItem::Kind::kConnected;
  connected.id = id;
  connected.value = agent->written_seq;
  batch->deliveries.push_back(std::move(connected));
  return Status::Ok();
}

void JournalStage::Data(StageItem* item, Batch* batch) {
  batch->freed[item->agent] += item->message.size();
  auto it = agents_.find(item->agent);
  if (it == agents_.end()) return;  // not possible: the I/O thread sends data after attach
  Agent& a = it->second;
  if (item->seq != a.written_seq + 1) {
    // Left over from a connection whose earlier record failed to store; the agent resends.
    stats_->Count("journal_out_of_sequence_dropped");
    return;
  }
  if (!a.writer) {
    const Status created = Persist(&a, batch);
    if (!created.ok()) {
      CCMD_LOG(ERROR) << "cannot create the journal of agent '" << a.info.name
                      << "': " << created.ToString();
      stats_->Count("journal_failures");
      std::lock_guard<std::mutex> lock(feedback_mutex_);
      feedback_.failed.emplace_back(item->agent, created);
      return;
    }
  }
  Status s = a.writer->Append(item->type, item->seq, item->message);
  if (!s.ok()) {
    StageFeedback unused;
    Fail(item->agent, s, batch, &unused);
    std::lock_guard<std::mutex> lock(feedback_mutex_);
    for (auto& f : unused.failed) feedback_.failed.push_back(std::move(f));
    return;
  }
  a.written_seq = item->seq;
  batch->touched[item->agent] = true;
  DeliveryItem d;
  d.kind = DeliveryItem::Kind::kMessage;
  d.message.agent = item->agent;
  d.message.seq = item->seq;
  d.message.type = item->type;
  d.message.payload = std::move(item->message);
  d.message.received_time = item->received_time;
  batch->deliveries.push_back(std::move(d));
}

Status JournalStageOptions::Validate() const {
  if (dir.empty()) return InvalidArgument("the journal stage needs a folder");
  if (max_agents < 1) return InvalidArgument("max_agents must be positive");
  if (queue_capacity == 0 || max_batch == 0) return InvalidArgument("queues need capacity");
  if (max_payload_bytes == 0) return InvalidArgument("max_payload_bytes must be positive");
  return Status::Ok();
}

void JournalStageOptions::Describe(OptionsWriter* out) const {
  out->Add("dir", dir);
  out->Add("fsync", fsync);
  out->Add("max_agents", max_agents);
  out->Add("slot_timeout_s", slot_timeout_s);
  out->Add("queue_capacity", queue_capacity);
  out->Add("max_batch", max_batch);
  out->Add("max_payload_bytes", max_payload_bytes);
}

}  // namespace ccmd
