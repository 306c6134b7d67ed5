#pragma once

// Small helpers shared by the report writers (replay_report.cc, replay_markdown.cc,
// replay_plots.cc, link_report.cc): numbers and strings out of results JSON, formatted
// numbers, an agent's entry in the server's traffic stats.

#include <cstdio>
#include <string>

#include "libccmd/util/json.h"

namespace ccmd::report {

// j[key] as a number; `fallback` when j is null, the key is missing or not a number.
inline double Num(const Json* j, const std::string& key, double fallback = 0) {
  if (!j) return fallback;
  const Json* v = j->Get(key);
  return v ? v->number(fallback) : fallback;
}

// j[key] as a string; "" when j is null or the key is missing.
inline std::string Str(const Json* j, const std::string& key) {
  const Json* v = j ? j->Get(key) : nullptr;
  return v ? v->string() : "";
}

// printf-style formatting of one number.
inline std::string Fmt(const char* format, double v) {
  char text[64];
  std::snprintf(text, sizeof(text), format, v);
  return text;
}

// The agent called `name` in server_stats.json's transport.agents; null if absent.
inline const Json* FindAgentTraffic(const Json& server_stats, const std::string& name) {
  const Json* transport = server_stats.Get("transport");
  const Json* agents = transport ? transport->Get("agents") : nullptr;
  if (!agents) return nullptr;
  for (const Json& a : agents->array()) {
    if (a.Get("name") && a.Get("name")->string() == name) return &a;
  }
  return nullptr;
}

}  // namespace ccmd::report
