#include "libccmd/system/bandwidth_budget.h"

#include <algorithm>
#include <cmath>

#include "libccmd/util/logging.h"

namespace ccmd {

std::vector<RgbdLevel> DefaultBudgetLadder(const RgbdEncodeOptions& base, int* default_level) {
  // Built outwards from the agent's own options in the order ccmd_knob_bench measured
  // (docs/benchmarks/link.md), on 7-Scenes and ICL-NUIM at ground-truth poses. Leaner: JPEG
  // quality costs the geometry nothing; r /2 costs about 1 point of completeness per kB saved
  // per keyframe; S_min x0.7 and x0.5 1.3 to 3.5 (whole views go); a coarser depth bound the
  // most (1 % adds 0.4 to 42 mm of mean error per kB). Richer: finer coding first (it lowers
  // the mean error: 11 to 5.6 mm on ICL-NUIM), then more views with RGB-D (the most
  // completeness per kB, but each overlapping view adds a little error), full resolution last.
  auto level = [&](std::string name, double scale, int downsample, int quality, int bound_e4,
                   bool every = false, bool allow = true) {
    RgbdLevel l;
    l.name = std::move(name);
    l.request.threshold_scale = scale;
    l.request.every_keyframe = every;
    l.request.allow = allow;
    l.encode = base;
    l.encode.downsample = downsample;
    l.encode.jpeg_quality = quality;
    l.encode.bound_e4 = bound_e4;
    return l;
  };
  const int r = base.downsample, q = base.jpeg_quality, e = base.bound_e4;
  const int finer_r = std::max(1, r / 2), coarser_r = std::min(4, r * 2);
  const int fine_q = std::max(q, 90), fine_e = std::max(1, e / 2);
  const int low_q = std::max(10, q - 25), lowest_q = std::max(10, q - 40),
            coarse_e = std::min(2000, e * 2);
  std::vector<RgbdLevel> ladder = {
      level("fine coding, every keyframe, r x2", 1, finer_r, fine_q, fine_e, true),
      level("fine coding, every keyframe", 1, r, fine_q, fine_e, true),
      level("fine coding, S_min x1.5", 1.5, r, fine_q, fine_e),
      level("fine coding", 1, r, fine_q, fine_e),
      level("agent settings", 1, r, q, e),
      level("JPEG q-25", 1, r, low_q, e),
      level("JPEG q-40", 1, r, lowest_q, e),
      level("JPEG q-40, r /2", 1, coarser_r, lowest_q, e),
      level("JPEG q-40, r /2, S_min x0.7", 0.7, coarser_r, lowest_q, e),
      level("JPEG q-40, r /2, S_min x0.5", 0.5, coarser_r, lowest_q, e),
      level("JPEG q-40, r /2, S_min x0.5, depth bound x2", 0.5, coarser_r, lowest_q, coarse_e),
      level("geometry only", 1, r, q, e, false, /*allow=*/false)};
  if (default_level) *default_level = 4;
  return ladder;
}

double RelativeRgbdSize(const RgbdEncodeOptions& encode) {
  // Coded bytes grow slower than the pixel count: halving r divides them by 2.6 to 2.9
  // (ccmd_knob_bench on 7-Scenes and ICL-NUIM), 4^0.72.
  const double pixels = std::pow(1.0 / (encode.downsample * encode.downsample), 0.72);
  const double colour = std::exp(0.021 * (encode.jpeg_quality - 75));
  const double depth = std::pow(50.0 / std::max(1, encode.bound_e4), 0.8);
  return pixels * (0.6 * colour + 0.4 * depth);
}

Status BandwidthBudgetOptions::Validate() const {
  if (!(budget_bytes_per_s >= 1000))
    return InvalidArgument("a bandwidth budget below 1 kB/s cannot carry a keyframe stream");
  if (!(max_queue_s > 0)) return InvalidArgument("the send queue bound must be positive");
  if (!(band_s > 0) || !(max_credit_s > band_s))
    return InvalidArgument("budget credit needs 0 < band < max credit");
  if (!(window_s > 0)) return InvalidArgument("the acknowledgement window must be positive");
  if (!(payload_share > 0 && payload_share <= 1))
    return InvalidArgument("payload share must be in (0, 1]");
  if (keyframe_scales.empty() || keyframe_scales.front() != 1.0 ||
      !std::is_sorted(keyframe_scales.rbegin(), keyframe_scales.rend()) ||
      !(keyframe_scales.back() > 0)) {
    return InvalidArgument("keyframe density scales must fall from 1 and stay above 0");
  }
  return Status::Ok();
}

void BandwidthBudgetOptions::Describe(OptionsWriter* out) const {
  out->Add("budget_bytes_per_s", budget_bytes_per_s);
  out->Add("max_queue_s", max_queue_s);
  out->Add("band_s", band_s);
  out->Add("max_credit_s", max_credit_s);
  out->Add("window_s", window_s);
  out->Add("payload_share", payload_share);
  out->Add("keyframe_scales", keyframe_scales);
}

BandwidthBudget::BandwidthBudget(const BandwidthBudgetOptions& options,
                                 std::vector<RgbdLevel> ladder, int start_level)
    : options_(options),
      ladder_(std::move(ladder)),
      level_(start_level),
      rgbd_bytes_(ladder_.size(), 0.0),
      keyframes_per_level_(ladder_.size(), 0),
      keyframes_per_density_(options_.keyframe_scales.size(), 0) {
  CCMD_CHECK(!options_.keyframe_scales.empty());
  CCMD_CHECK(!ladder_.empty() &&
             !ladder_.back().request.allow);  // the last rung sends geometry only
  CCMD_CHECK(start_level >= 0 && start_level < static_cast<int>(ladder_.size()));
}

void BandwidthBudget::Observe(const LinkObservation& link) {
  const double budget = PacedBudget();
  if (!started_) {
    started_ = true;
    start_s_ = last_s_ = link.now_s;
    last_handed_ = link.handed_bytes;
    credit_bytes_ = options_.band_s * budget;  // neither richer nor leaner before sizes are known
  }
  const std::uint64_t acked = link.handed_bytes - std::min(link.handed_bytes, link.unacked_bytes);
  samples_.push_back({link.now_s, acked, link.unacked_bytes});
  while (samples_.size() > 2 && samples_[1].t <= link.now_s - options_.window_s)
    samples_.erase(samples_.begin());
  // The rate the server acknowledges at says what the link gives only while there was
  // always something waiting for it.
  const Sample& oldest = samples_.front();
  const bool backlogged =
      std::all_of(samples_.begin(), samples_.end(), [](const Sample& s) { return s.unacked > 0; });
  const double span = link.now_s - oldest.t;
  link_rate_ = backlogged && span >= 0.5 * options_.window_s ? (acked - oldest.acked) / span : -1.0;
  // A stalled link (backlogged, nothing acknowledged) earns no credit.
  const double fill = link_rate_ >= 0 ? std::min(budget, link_rate_) : budget;
  credit_bytes_ += fill * std::max(0.0, link.now_s - last_s_) -
                   static_cast<double>(link.handed_bytes - last_handed_);
  credit_bytes_ = std::min(credit_bytes_, options_.max_credit_s * budget);
  last_s_ = link.now_s;
  last_handed_ = link.handed_bytes;
}

BudgetDecision BandwidthBudget::Measure(const LinkObservation& link, double* rate) {
  Observe(link);
  const double budget = PacedBudget();
  // Queue time at the rate the link gives (a stalled one counts as 5 % of the budget, so its
  // queue reads as long, not infinite).
  *rate = link_rate_ >= 0 ? std::max(0.05 * budget, std::min(link_rate_, budget)) : budget;
  BudgetDecision d;
  d.time_s = link.now_s - start_s_;
  d.queue_s = link.unacked_bytes / *rate;
  d.credit_s = credit_bytes_ / budget;
  d.link_rate_bytes_per_s = std::max(0.0, link_rate_);
  return d;
}

bool BandwidthBudget::RoomForDenser(const BudgetDecision& d) const {
  return density_ > 0 && d.credit_s > options_.band_s && d.queue_s <= options_.max_queue_s;
}

void BandwidthBudget::Refresh(const LinkObservation& link) {
  double rate;
  // Only denser here: thinner needs a keyframe's bytes to show the debt growing.
  if (RoomForDenser(Measure(link, &rate))) --density_;
}

const RgbdLevel& BandwidthBudget::Plan(const LinkObservation& link) {
  double rate;
  BudgetDecision d = Measure(link, &rate);
  if (last_plan_s_ >= 0 && link.now_s > last_plan_s_) {
    const double interval = link.now_s - last_plan_s_;
    keyframe_interval_s_ =
        keyframe_interval_s_ > 0 ? 0.7 * keyframe_interval_s_ + 0.3 * interval : interval;
  }
  last_plan_s_ = link.now_s;
  const double budget = PacedBudget();
  max_queue_seen_s_ = std::max(max_queue_seen_s_, d.queue_s);
  const int leanest = static_cast<int>(ladder_.size()) - 1;
  // The queue bound holds at least two keyframes' geometry: below that, a small budget could
  // never carry any RGB-D, however slowly keyframes came.
  const double bound_s = std::max(options_.max_queue_s, 2 * geometry_bytes_ / rate);
  // Geometry alone over the budget at the keyframes' pace: no level with RGB-D helps.
  const bool geometry_overflows =
      keyframe_interval_s_ > 0 && geometry_bytes_ > budget * keyframe_interval_s_;
  if (geometry_overflows && d.credit_s < -options_.band_s) level_ = leanest;
  StepDensity(d, previous_credit_s_);
  previous_credit_s_ = d.credit_s;
  if (density_ > 0) {
    level_ = leanest;  // keyframes are being thinned: no RGB-D
  } else if (d.credit_s < -options_.band_s) {
    level_ = std::min(level_ + 1, leanest);
  } else if (d.credit_s > options_.band_s) {
    // The richest level the credit pays for (unused credit beyond max_credit_s is lost);
    // never richer on a guess: only once some RGB-D keyframe has shown what they cost.
    const double floor = -options_.band_s * budget;
    for (int richer = level_ - 1; richer >= 0; --richer) {
      const double expected = ExpectedRgbdBytes(richer);
      if (expected < 0 || credit_bytes_ - geometry_bytes_ - expected < floor) break;
      level_ = richer;
    }
  }
  // What is left of the queue bound, in bytes at the link's rate: the keyframe must fit.
  const double room = bound_s * rate - static_cast<double>(link.unacked_bytes) - geometry_bytes_;
  while (level_ < leanest && ExpectedRgbdBytes(level_) > room) ++level_;
  d.level = level_;
  if (d.queue_s > bound_s) {
    // Geometry alone keeps the queue over its bound: nothing optional until it drains.
    d.shed = true;
    d.level = leanest;
    ++shed_;
  }
  d.keyframe_scale = KeyframeRatioScale();
  current_ = d;
  pending_ = true;
  return ladder_[d.level];
}

void BandwidthBudget::StepDensity(const BudgetDecision& d, double previous_credit_s) {
  const int leanest = static_cast<int>(ladder_.size()) - 1;
  const int thinnest = static_cast<int>(options_.keyframe_scales.size()) - 1;
  // Over the budget, not merely waiting for a keyframe in flight: the credit says so (it
  // accrues at the link's rate when the link is slower than the budget). Thinner while the
  // debt still grows from one keyframe to the next (the keyframes at this density bring more
  // geometry than the budget accrues between them); denser as soon as the credit allows,
  // since unused credit beyond max_credit_s is lost.
  const bool debt_grows = d.credit_s < -options_.band_s && d.credit_s < previous_credit_s;
  if (level_ == leanest && debt_grows && density_ < thinnest) {
    ++density_;
  } else if (RoomForDenser(d)) {
    --density_;
  }
}

double BandwidthBudget::ExpectedRgbdBytes(int level) const {
  if (!ladder_[level].request.allow) return 0;
  if (rgbd_bytes_[level] > 0) return rgbd_bytes_[level];
  for (int distance = 1; distance < static_cast<int>(ladder_.size()); ++distance) {
    for (const int l : {level + distance, level - distance}) {
      if (l >= 0 && l < static_cast<int>(ladder_.size()) && rgbd_bytes_[l] > 0) {
        return rgbd_bytes_[l] * RelativeRgbdSize(ladder_[level].encode) /
               RelativeRgbdSize(ladder_[l].encode);
      }
    }
  }
  return -1;  // nothing seen yet: the first RGB-D keyframe teaches the sizes
}

void BandwidthBudget::Record(KeyframeId keyframe, std::uint64_t message_bytes,
                             std::uint64_t rgbd_bytes, bool rgbd) {
  if (!pending_) return;  // a keyframe without a plan (the sink was not asked): nothing to add
  pending_ = false;
  BudgetDecision& d = current_;
  // Running means (weight 0.3 for the newest): sizes follow the scene.
  auto update = [](double* mean, double sample) {
    *mean = *mean > 0 ? 0.7 * *mean + 0.3 * sample : sample;
  };
  update(&geometry_bytes_, static_cast<double>(message_bytes - rgbd_bytes));
  if (rgbd) update(&rgbd_bytes_[d.level], static_cast<double>(rgbd_bytes));
  d.keyframe = keyframe;
  d.message_bytes = message_bytes;
  d.rgbd_bytes = rgbd_bytes;
  d.rgbd = rgbd;
  ++keyframes_per_level_[d.level];
  ++keyframes_per_density_[density_];
  if (decisions_.size() < kMaxRecorded) {
    decisions_.push_back(d);
  } else {
    ++not_recorded_;
  }
}

Json BandwidthBudget::ToJson() const {
  Json j;
  j["budget_kBps"] = options_.budget_bytes_per_s / 1e3;
  j["queue_bound_s"] = options_.max_queue_s;
  j["queue_max_s"] = max_queue_seen_s_;
  j["shed_keyframes"] = shed_;
  Json ladder = Json::MakeArray();
  for (const RgbdLevel& l : ladder_) {
    Json e;
    e["name"] = l.name;
    e["allow"] = l.request.allow;
    e["every_keyframe"] = l.request.every_keyframe;
    e["threshold_scale"] = l.request.threshold_scale;
    e["r"] = 1.0 / l.encode.downsample;
    e["jpeg_quality"] = l.encode.jpeg_quality;
    e["depth_bound"] = l.encode.bound_e4 / 1e4;
    ladder.Push(e);
  }
  j["ladder"] = ladder;
  Json list = Json::MakeArray();
  for (const BudgetDecision& d : decisions_) {
    Json e;
    e["keyframe"] = d.keyframe.value();
    e["t"] = d.time_s;
    e["level"] = d.level;
    e["keyframe_scale"] = d.keyframe_scale;
    e["shed"] = d.shed;
    e["credit_s"] = d.credit_s;
    e["queue_s"] = d.queue_s;
    e["link_kBps"] = d.link_rate_bytes_per_s / 1e3;
    e["bytes"] = d.message_bytes;
    e["rgbd_bytes"] = d.rgbd_bytes;
    e["rgbd"] = d.rgbd;
    list.Push(e);
  }
  j["decisions"] = list;
  j["decisions_not_recorded"] = not_recorded_;
  Json histogram = Json::MakeArray();
  for (int n : keyframes_per_level_) histogram.Push(n);
  j["keyframes_per_level"] = histogram;
  Json density = Json::MakeArray();
  for (std::size_t i = 0; i < keyframes_per_density_.size(); ++i) {
    Json e;
    e["keyframe_scale"] = options_.keyframe_scales[i];
    e["keyframes"] = keyframes_per_density_[i];
    density.Push(e);
  }
  j["keyframes_per_density"] = density;
  return j;
}

}  // namespace ccmd
