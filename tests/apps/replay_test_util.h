#pragma once

// Running ccmd_replay from the end-to-end tests and checking its headline figures.

#include <gtest/gtest.h>

#include <string>

#include "libccmd/util/json.h"
#include "libccmd/util/status.h"
#include "tests/support/test_support.h"

namespace ccmd::testing {

// ccmd_replay on `dataset` with `agents` agents (and `config` unless empty) into `out`:
// results.json, or an error; `log` gets the program's output either way.
inline StatusOr<Json> RunReplay(const std::string& dataset, int agents, const std::string& config,
                                const std::string& out, std::string* log) {
  std::string command = ProgramPath("ccmd_replay") + " --dataset " + dataset + " --agents " +
                        std::to_string(agents) + " --out " + out;
  if (!config.empty()) command += " --config " + config;
  const int code = RunCommand(command, log);
  if (code != 0) return Internal("ccmd_replay exited with " + std::to_string(code));
  return ReadJsonFile(out + "/results.json");
}

// One map at the end, with a fused ATE and a reconstruction error below the bounds.
inline void ExpectFusedWithin(const Json& results, double max_ate_m, double max_recon_mean_m,
                              const std::string& log) {
  EXPECT_EQ(results.Get("maps_after_fusion")->number(), 1) << log;
  ASSERT_TRUE(results.Has("ate_rmse_m")) << log;
  ASSERT_TRUE(results.Has("recon_mean_m")) << log;
  EXPECT_LT(results.Get("ate_rmse_m")->number(), max_ate_m);
  EXPECT_LT(results.Get("recon_mean_m")->number(), max_recon_mean_m);
}

}  // namespace ccmd::testing
