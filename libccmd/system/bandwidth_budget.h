#pragma once

// The agent's bandwidth budget (ccmd_agent --bandwidth-budget). Keyframe geometry always
// goes; what the budget adapts is the optional RGB-D part, through a ladder of levels from
// the richest (RGB-D with every keyframe, full resolution, fine coding) through the agent's
// own settings down to geometry only. The order in which the knobs give way (JPEG quality,
// depth error bound, sampling rate r, selection threshold S_min) follows what each costs the
// dense map per byte saved (docs/benchmarks/link.md).
//
// Before each keyframe's RGB-D decision the budget looks at the link:
//   credit  budget accrued minus bytes handed to the link, at most max_credit_s of budget
//           saved up; the budget accrues at the lower of the budget and the rate the server
//           acknowledges at while the link is backlogged (what the link really gives);
//   queue   bytes not yet acknowledged, in seconds at that rate.
// A credit below -band_s of budget steps one level leaner, above +band_s to the richest
// level whose keyframe the credit pays for. Whatever the credit, the level is then
// made lean enough that the keyframe fits in what is left of the queue bound (max_queue_s,
// or two keyframes' geometry if that takes longer) at the link's rate (sizes are learnt per level;
// unseen levels are estimated from seen ones), so the send queue, and with it the keyframes' wait,
// stays bounded in time. When geometry alone overflows it, the keyframe goes without RGB-D and the
// queue grows: geometry is never dropped, and the decisions say so. Every decision is recorded. The
// wire itself is paced at the budget by the link (AgentLinkOptions::max_send_bytes_per_s).
//
// Below the geometry-only rung the budget thins the keyframes themselves: while geometry
// alone overflows (credit below the band at the leanest rung, reached at once when geometry
// alone exceeds the budget at the keyframes' pace) and the debt still grows from one keyframe
// to the next, it steps the keyframe density down; KeyframeRatioScale() multiplies the fraction
// of tracked points under which the tracker makes a keyframe, and each 0.1 off that fraction
// about halves the keyframes (docs/benchmarks/frontend.md) at little cost in accuracy. Every
// keyframe made still goes whole. Density comes back first, before any RGB-D, once the credit
// is above the band and the queue within max_queue_s.
//
// No clock of its own and no threads: callers pass observations, so tests are exact.

#include <cstdint>
#include <string>
#include <vector>

#include "libccmd/codec/rgbd_payload.h"
#include "libccmd/tracking/keyframe_sink.h"
#include "libccmd/util/ids.h"
#include "libccmd/util/json.h"
#include "libccmd/util/options_writer.h"
#include "libccmd/util/status.h"

namespace ccmd {

// One rung: what the selection is asked and how the RGB-D payload is coded.
struct RgbdLevel {
  std::string name;
  RgbdRequest request;
  RgbdEncodeOptions encode;
};

// The shipped ladder around the agent's own coding options `base`; *default_level is the
// index of the level equal to `base` with the selection as configured.
std::vector<RgbdLevel> DefaultBudgetLadder(const RgbdEncodeOptions& base, int* default_level);

// A rough model of an RGB-D payload's size relative to r = 1, JPEG quality 75, depth bound
// 0.5 % (docs/benchmarks/codec.md and link.md: bytes about as pixels^0.72, colour about 60 %
// of them growing about 2 % per JPEG quality step, bounded depth about as bound^-0.8), for
// levels not seen yet.
double RelativeRgbdSize(const RgbdEncodeOptions& encode);

struct BandwidthBudgetOptions {
  double budget_bytes_per_s = 0;
  // Send queue bound: at least this, and two keyframes' geometry at the budget. Longer: no
  // RGB-D until it drains; each keyframe's RGB-D must fit in what is left of it. At 0.5 s a
  // 100 kB/s budget left about 32 kB beside a keyframe's geometry, less than one keyframe at
  // the finer levels, and the agents used 80 to 90 % of their budgets (docs/benchmarks/link.md).
  double max_queue_s = 1.0;
  double band_s = 0.25;       // credit dead band, in seconds of budget
  double max_credit_s = 1.0;  // unused budget kept for later, in seconds of budget
  double window_s = 2.0;      // acknowledgement rate measured over this window
  // Message bytes aim at this share of the budget: the pacing counts whole TCP/IP packets.
  double payload_share = 0.96;
  // Keyframe densities below geometry only, as scales of the tracked-point fraction, from
  // the tracker's own (1) down.
  std::vector<double> keyframe_scales = {1.0, 0.8, 0.64, 0.5};
  Status Validate() const;
  void Describe(OptionsWriter* out) const;
};

// What the agent's link reports (AgentLink::stats and the bytes handed to it).
struct LinkObservation {
  double now_s = 0;                 // monotonic
  std::uint64_t handed_bytes = 0;   // message bytes handed to the link so far
  std::uint64_t unacked_bytes = 0;  // of those, not yet acknowledged by the server
};

struct BudgetDecision {
  KeyframeId keyframe;
  double time_s = 0;  // since the first observation
  int level = 0;
  double keyframe_scale = 1;  // the keyframe density asked of the tracker after this decision
  bool shed = false;          // RGB-D withheld because the queue was too long
  double credit_s = 0, queue_s = 0, link_rate_bytes_per_s = 0;
  std::uint64_t message_bytes = 0, rgbd_bytes = 0;
  bool rgbd = false;  // the keyframe carried RGB-D
};

class BandwidthBudget {
 public:
  BandwidthBudget(const BandwidthBudgetOptions& options, std::vector<RgbdLevel> ladder,
                  int start_level);

  // The level for the next keyframe (recorded, to be completed by Record).
  const RgbdLevel& Plan(const LinkObservation& link);
  // Between keyframes (the tracker asks for the density every frame): takes in the link and
  // makes the keyframes denser if the credit has come back; no keyframe is planned. Without
  // it a thinned agent whose camera slows down would make no keyframe to plan at, and its
  // unused budget would be lost.
  void Refresh(const LinkObservation& link);
  // The keyframe the last plan went to, as it was sent.
  void Record(KeyframeId keyframe, std::uint64_t message_bytes, std::uint64_t rgbd_bytes,
              bool rgbd);

  // The recorded decisions: the first kMaxRecorded (a run's memory must not grow without
  // end; the counts per level and the queue figures cover every keyframe).
  const std::vector<BudgetDecision>& decisions() const { return decisions_; }
  static constexpr std::size_t kMaxRecorded = 100000;
  const std::vector<RgbdLevel>& ladder() const { return ladder_; }
  // Multiplies the tracker's keyframe fraction (1: its own density; below: fewer keyframes).
  double KeyframeRatioScale() const { return options_.keyframe_scales[density_]; }
  Json ToJson() const;

 private:
  void Observe(const LinkObservation& link);
  // The budget in message bytes per second (the share of it the pacing leaves for messages).
  double PacedBudget() const { return options_.budget_bytes_per_s * options_.payload_share; }
  // Observes the link and fills a decision's time, queue, credit and link rate; `rate` gets
  // the rate the queue is measured at.
  BudgetDecision Measure(const LinkObservation& link, double* rate);
  // The credit is back above the band and the queue within its bound: one step denser.
  bool RoomForDenser(const BudgetDecision& d) const;
  // One step of keyframe density: thinner while geometry alone overflows at the leanest rung
  // and the debt grows since the last plan, back once the credit is above the band.
  void StepDensity(const BudgetDecision& d, double previous_credit_s);
  // Bytes of RGB-D a keyframe sent at `level` is expected to carry (learnt per level; a level
  // not seen yet is estimated from the nearest one seen, by RelativeRgbdSize); -1 before any
  // RGB-D keyframe was seen.
  double ExpectedRgbdBytes(int level) const;

  BandwidthBudgetOptions options_;
  std::vector<RgbdLevel> ladder_;
  int level_;
  int density_ = 0;  // index into keyframe_scales
  double previous_credit_s_ = 0;
  bool started_ = false;
  double start_s_ = 0, last_s_ = 0;
  std::uint64_t last_handed_ = 0;
  double credit_bytes_ = 0;
  double link_rate_ = -1;  // acknowledged bytes per second while backlogged; < 0 = not measured
  struct Sample {
    double t;
    std::uint64_t acked, unacked;
  };
  std::vector<Sample> samples_;     // within window_s
  double geometry_bytes_ = 0;       // running mean of a keyframe without its RGB-D
  double keyframe_interval_s_ = 0;  // running mean of the time between two plans
  double last_plan_s_ = -1;
  std::vector<double> rgbd_bytes_;  // running mean per level; 0 = not seen
  double max_queue_seen_s_ = 0;
  int shed_ = 0;
  std::vector<int> keyframes_per_level_;
  std::vector<int> keyframes_per_density_;
  BudgetDecision current_;  // planned, waiting for Record
  bool pending_ = false;
  std::vector<BudgetDecision> decisions_;
  std::uint64_t not_recorded_ = 0;
};

}  // namespace ccmd
