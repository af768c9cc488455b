// Read an MCAP bag with Foxglove's reader, decode every ROS 2 message with Foxglove's CDR
// decoder and report, per topic, how many messages it decoded and how many left bytes unread
// (MessageReader.lastReadHadTrailingBytes). Prints one JSON object; exit 0 when every message
// decoded, 1 otherwise (an undecodable message is reported, not thrown).
//   node check_bag.cjs <file.mcap>
'use strict';
const fs = require('fs');
const { McapStreamReader } = require('@mcap/core');
const { loadDecompressHandlers } = require('@mcap/support');
const { parse } = require('@foxglove/rosmsg');
const { MessageReader } = require('@foxglove/rosmsg2-serialization');

async function main(path) {
  const reader = new McapStreamReader({ decompressHandlers: await loadDecompressHandlers() });
  reader.append(fs.readFileSync(path));
  const schemas = new Map();
  const decoders = new Map();
  const topics = {};
  let failed = false;
  for (let record; (record = reader.nextRecord()); ) {
    if (record.type === 'Schema') {
      schemas.set(record.id, record);
    } else if (record.type === 'Channel' && !decoders.has(record.id)) {  // summary repeats it
      const schema = schemas.get(record.schemaId);
      const text = new TextDecoder().decode(schema.data);
      decoders.set(record.id, { topic: record.topic,
                                reader: new MessageReader(parse(text, { ros2: true })) });
      topics[record.topic] = { messages: 0, trailing: 0, errors: [] };
    } else if (record.type === 'Message') {
      const { topic, reader: decoder } = decoders.get(record.channelId);
      const counts = topics[topic];
      counts.messages += 1;
      try {
        decoder.readMessage(record.data);
        if (decoder.lastReadHadTrailingBytes()) {
          counts.trailing += 1;
        }
      } catch (error) {
        failed = true;
        if (counts.errors.length < 3) counts.errors.push(String(error));
      }
    }
  }
  if (!reader.done()) {
    failed = true;
  }
  process.stdout.write(JSON.stringify({ complete: reader.done(), topics }) + '\n');
  return failed ? 1 : 0;
}

main(process.argv[2]).then((code) => process.exit(code), (error) => {
  process.stderr.write(`check_bag: ${error}\n`);
  process.exit(2);
});
