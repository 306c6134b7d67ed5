#include "tests/support/server_with_view.h"

#include "libccmd/util/string_util.h"

namespace ccmd::testing {

StatusOr<ServerWithView> StartServerWithView(const std::string& program, const std::string& folder,
                                             const std::vector<std::string>& extra_args) {
  std::vector<std::string> argv = {
      program, "--listen",          "127.0.0.1:0", "--journal",   folder + "/journal",
      "--out", folder + "/results", "--http",      "127.0.0.1:0", "--no-fsync"};
  argv.insert(argv.end(), extra_args.begin(), extra_args.end());
  CCMD_ASSIGN_OR_RETURN(Subprocess process,
                        Subprocess::Start(argv, "", folder + "/server.log", /*pipe_stdout=*/true));
  ServerWithView server{std::move(process), "", 0, 0};
  while (server.port == 0) {
    CCMD_ASSIGN_OR_RETURN(const std::string line, server.process.ReadLine(120));
    if (StartsWith(line, "map view: ")) {
      server.url = line.substr(10);
      const std::size_t colon = server.url.rfind(':');
      CCMD_ASSIGN_OR_RETURN(
          const long long port,
          ParseInt(server.url.substr(colon + 1, server.url.find('/', colon) - colon - 1)));
      server.view_port = static_cast<std::uint16_t>(port);
    }
    const std::size_t at = line.find("listening on ");
    if (at != std::string::npos) {
      CCMD_ASSIGN_OR_RETURN(const long long port, ParseInt(line.substr(line.rfind(':') + 1)));
      server.port = static_cast<std::uint16_t>(port);
    }
  }
  if (server.url.empty()) return Internal("ccmd_server printed no map view address");
  server.process.DrainStdoutTo(folder + "/server.out");
  return server;
}

}  // namespace ccmd::testing
