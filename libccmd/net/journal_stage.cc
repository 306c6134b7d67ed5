#include "libccmd/net/journal_stage.h"

#include <dirent.h>
#include <unistd.h>

#include <algorithm>

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
    JournalScanOptions scan_options{.max_payload_bytes = options_.max_payload_bytes};
    CCMD_ASSIGN_OR_RETURN(const JournalScan scan, ScanJournalFile(path, visitor, scan_options));
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
    agent.written_seq = agent.durable_seq = scan.last_seq;
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
      case StageItem::Kind::kDetach: {
        DeliveryItem d;
        d.kind = DeliveryItem::Kind::kDisconnected;
        d.id = item.agent;
        d.reason = item.reason;
        batch.deliveries.push_back(std::move(d));
        break;
      }
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
  {
    std::lock_guard<std::mutex> lock(feedback_mutex_);
    for (AttachResult& r : feedback.attached) feedback_.attached.push_back(std::move(r));
    for (const auto& [id, seq] : feedback.stored) feedback_.stored[id] = seq;
    for (const auto& [id, n] : feedback.freed_bytes) feedback_.freed_bytes[id] += n;
    for (auto& f : feedback.failed) feedback_.failed.push_back(std::move(f));
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

void JournalStage::Attach(const StageItem& item, Batch* batch) {
  const HelloMessage& hello = item.hello;
  AttachResult result;
  result.conn = item.conn;
  auto refuse = [&](ByeReason reason, Status status) {
    result.status = std::move(status);
    result.reason = reason;
    batch->attached.push_back(std::move(result));
  };
  Agent* agent = nullptr;
  auto found = by_name_.find(hello.name);
  if (found != by_name_.end()) {
    agent = &agents_[found->second];
    if (!(agent->info.camera == hello.camera)) {
      return refuse(ByeReason::kRefused,
                    InvalidArgument("agent '" + hello.name + "' is registered with camera " +
                                    DescribeCamera(agent->info.camera) + " but announces " +
                                    DescribeCamera(hello.camera) +
                                    "; a different camera needs a new agent name"));
    }
  } else {
    if (static_cast<int>(agents_.size()) >= options_.max_agents) {
      return refuse(ByeReason::kServerFull,
                    OutOfRange("the server has " + std::to_string(agents_.size()) +
                               " agents registered, its limit (--max-agents)"));
    }
    const AgentId id(agents_.empty() ? 1 : agents_.rbegin()->first.value() + 1);
    if (id.value() == 0) {
      return refuse(ByeReason::kServerFull, OutOfRange("agent ids exhausted"));
    }
    JournalAgentInfo info{id, hello.name, hello.camera};
    StatusOr<std::unique_ptr<JournalWriter>> writer =
        JournalWriter::Create(JoinPath(options_.dir, JournalFileName(id)), info);
    if (!writer.ok()) {
      CCMD_LOG(ERROR) << "cannot register agent '" << hello.name
                      << "': " << writer.status().ToString();
      return refuse(ByeReason::kServerError, writer.status());
    }
    Agent a;
    a.info = info;
    a.writer = std::move(*writer);
    by_name_[hello.name] = id;
    agent = &(agents_[id] = std::move(a));
    CCMD_LOG(INFO) << "registered agent " << id << " '" << hello.name << "' ("
                   << DescribeCamera(hello.camera) << ")";
  }
  std::uint64_t last = agent->written_seq;
  if (!hello.fresh) {
    if (hello.next_seq - 1 < last) {
      return refuse(
          ByeReason::kRefused,
          InvalidArgument("the server holds " + std::to_string(last) + " messages of agent '" +
                          hello.name + "' but the agent has sent only " +
                          std::to_string(hello.next_seq - 1) +
                          "; is another agent using the same name?"));
    }
    if (hello.first_seq > last + 1) {
      // The agent no longer holds messages last+1 .. first_seq-1: they were acknowledged by
      // a server whose journal is not here (started without --resume, or a lost folder).
      CCMD_LOG(WARNING) << "agent '" << hello.name << "': messages " << last + 1 << ".."
                        << hello.first_seq - 1
                        << " were acknowledged earlier but are not in this server's journal "
                           "(started without its --resume folder?); continuing after the gap";
      stats_->Count("sequence_gaps");
      agent->written_seq = agent->durable_seq = hello.first_seq - 1;
      last = agent->written_seq;
    }
  }
  Announce(agent, /*from_journal=*/false, &batch->deliveries).IgnoreError();
  DeliveryItem connected;
  connected.kind = DeliveryItem::Kind::kConnected;
  connected.id = agent->info.id;
  connected.value = last;
  batch->deliveries.push_back(std::move(connected));
  result.agent = agent->info.id;
  result.last_stored = last;
  batch->attached.push_back(std::move(result));
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
  out->Add("queue_capacity", queue_capacity);
  out->Add("max_batch", max_batch);
  out->Add("max_payload_bytes", max_payload_bytes);
}

}  // namespace ccmd
