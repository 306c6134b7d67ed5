#pragma once

// A ccmd_server process with its live map view on loopback (free ports for both), for the
// view's browser test and benchmark.

#include <cstdint>
#include <string>
#include <vector>

#include "libccmd/util/status.h"
#include "libccmd/util/subprocess.h"

namespace ccmd::testing {

struct ServerWithView {
  Subprocess process;
  std::string url;              // "map view: ..." as printed
  std::uint16_t port = 0;       // agents connect here
  std::uint16_t view_port = 0;  // the view's HTTP port
};

// Starts ccmd_server (`program`) with a journal and results in `folder` (its log in
// folder/server.log) and waits for its "map view" and "listening on" lines.
StatusOr<ServerWithView> StartServerWithView(const std::string& program, const std::string& folder,
                                             const std::vector<std::string>& extra_args = {});

}  // namespace ccmd::testing
